"""A clean-room image-formation path for checking fieldcal on stacks it did not render (session 8).

Nothing here imports or follows ``fieldcal.simulate``, ``fieldcal.optics`` or ``fieldcal.charts``: the lens
description, the pupil-function OTF, the charts, the truth and the noise are written from textbook optics
(Goodman, *Introduction to Fourier Optics*; Hopkins 1955 for the defocus OTF) with numpy/scipy/OpenCV only.
fieldcal is used only as a user would: the stack folder format and ``calibrate`` / profile / plan calls.

Modules: ``lens`` (the lens description), ``otf`` (pupil → OTF, FFT and quadrature), ``chart`` (dead leaves
and slanted-edge squares, supersampled 8x and area-averaged), ``render`` (field-varying blur by PSF blending
between grid nodes, pixel aperture, noise), ``truth`` (through-focus MTF(fs) peaks and δ per node),
``stackio`` (writes ``fieldcal-stack/1``), ``evaluate`` (fieldcal's profile against the truth).
"""
