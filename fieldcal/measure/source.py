"""What measurement reads: any :class:`fieldcal.formats.frames.FrameSource`.

The on-disk :class:`fieldcal.formats.stack.Stack` and the in-memory :class:`ArrayStack` are the two sources;
both live in :mod:`fieldcal.formats` (one reader interface for measurement and compositing).
"""

from ..formats.frames import ArrayStack, FrameSource

__all__ = ["ArrayStack", "FrameSource"]
