"""Capture: acquisition plans as inspectable message streams, the one runner that executes them, and the
acquisition that owns devices and signals. See docs/architecture.md ("Capture: plans are message streams").

``CapturePlan`` (what to take) -> ``CapturePlan.messages()`` (a stream of ``Move``, ``WaitOnTarget``,
``Settle``, ``Expose``, ``Save``, ...) -> checked by ``stream.check_against_stage``, printed by the dry run and
executed by ``Runner`` inside an ``Acquisition`` into a locked, resumable ``CaptureFolder``.
"""

from .acquisition import Acquisition, CaptureResult, Interrupted, LensRecord, RunOptions, capture, run_capture
from .folder import JOURNAL, JOURNAL_FORMAT, CaptureFolder
from .messages import (Checkpoint, CloseExposure, Expose, Message, Move, OpenExposure, Save, Settle, SweepMove,
                       WaitOnTarget)
from .plan import CapturePlan, PlannedFrame
from .runner import Runner

__all__ = ["Acquisition", "CaptureFolder", "CapturePlan", "CaptureResult", "Checkpoint", "CloseExposure", "Expose",
           "Interrupted", "JOURNAL", "JOURNAL_FORMAT", "LensRecord", "Message", "Move", "OpenExposure", "PlannedFrame",
           "RunOptions", "Runner", "Save", "Settle", "SweepMove", "WaitOnTarget", "capture", "run_capture"]
