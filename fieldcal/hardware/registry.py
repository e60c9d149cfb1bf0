"""Device strings -> device objects, with plug-ins.

A device string is ``KIND[:ARG][,key=value...]``: ``sim``, ``sim:fail_after=7``, ``gcs:/dev/ttyUSB0,axis=1``,
``sim:models/triplet-uncorrected.json,size=320x180``. ``KIND`` names a backend registered under the entry-point
group ``fieldcal.stages`` or ``fieldcal.cameras``; a lab adds its own with, in its package's pyproject.toml::

    [project.entry-points."fieldcal.stages"]
    mystage = "mylab.devices:MyStage"

The object an entry point names is either a class with ``from_spec(arg, options) -> device`` or any callable
``f(arg, **options) -> device``. fieldcal's own backends are also built in here, so they work even when the
package metadata is stale (an editable install made before an entry point was added).
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from typing import Any

from ..errors import ParameterError

GROUPS = {"stage": "fieldcal.stages", "camera": "fieldcal.cameras", "exposure": "fieldcal.exposure_devices"}
BUILTIN = {
    "stage": {"sim": "fieldcal.hardware.sim:SimStage", "gcs": "fieldcal.hardware.gcs2:GCS2Stage",
              "pi": "fieldcal.hardware.pipython_backend:PipythonStage"},
    "camera": {"sim": "fieldcal.hardware.sim:SimCamera", "pylon": "fieldcal.hardware.camera_pylon:PylonCamera"},
    "exposure": {"sim": "fieldcal.hardware.sim:SimExposureDevice"},
}


def parse_device_string(text: str) -> tuple[str, str | None, dict[str, str]]:
    """``"gcs:/dev/ttyUSB0,axis=1"`` -> ``("gcs", "/dev/ttyUSB0", {"axis": "1"})``.

    The first comma-separated item after ``KIND:`` that has no ``=`` is the positional argument (a port or a
    file); ``key=value`` items are options. Only the first ``:`` splits, so ``socket://host:port`` and
    ``C:\\lens.json`` survive.
    """
    text = text.strip()
    if not text:
        raise ParameterError("empty device string", fix="write e.g. sim, sim:fail_after=7 or gcs:/dev/ttyUSB0")
    kind, _, rest = text.partition(":")
    arg: str | None = None
    options: dict[str, str] = {}
    if rest:
        for item in rest.split(","):
            item = item.strip()
            if not item:
                continue
            if "=" in item and not item.startswith("socket://"):
                k, _, v = item.partition("=")
                options[k.strip()] = v.strip()
            elif arg is None:
                arg = item
            else:
                raise ParameterError(f"device string '{text}' has two arguments ('{arg}' and '{item}')",
                                     fix="give one port/file, then key=value options, separated by commas")
    return kind.strip().lower(), arg, options


def _load(ref: str):
    mod, _, attr = ref.partition(":")
    return getattr(importlib.import_module(mod), attr)


def available(role: str) -> dict[str, str]:
    """Backend names for ``role`` ("stage", "camera" or "exposure") -> where they come from."""
    found = {name: ref for name, ref in BUILTIN[role].items()}
    for ep in entry_points(group=GROUPS[role]):
        found[ep.name] = ep.value
    return found


def make_device(role: str, text: str) -> Any:
    """Build (not connect) the stage or camera a device string names."""
    kind, arg, options = parse_device_string(text)
    eps = {ep.name: ep for ep in entry_points(group=GROUPS[role])}
    if kind in eps:
        factory = eps[kind].load()
    elif kind in BUILTIN[role]:
        factory = _load(BUILTIN[role][kind])
    else:
        names = ", ".join(sorted(available(role)))
        raise ParameterError(f"no {role} backend called '{kind}'", field=role,
                             fix=f"use one of: {names}; or register one under the entry-point group "
                                 f"'{GROUPS[role]}' (docs/hardware.md)")
    if hasattr(factory, "from_spec"):
        return factory.from_spec(arg, options)
    return factory(arg, **options)
