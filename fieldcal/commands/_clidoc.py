"""Print docs/cli.md's reference section from the real parsers: ``python -m fieldcal.commands._clidoc``."""

from __future__ import annotations

import argparse
import io
import os

INTRO = """# The command line

One entry point, `fieldcal`, with a subcommand per pipeline stage. Every subcommand has `--help` with an
example; long work shows progress on stderr (silence it with `FIELDCAL_PROGRESS=0`); user mistakes end in a
one-paragraph message that names the file, the field and the fix, and a non-zero exit status:

| exit | meaning |
| --- | --- |
| 0 | done |
| 1 | `validate`: a check failed (the report says which); `profile diff --fail-if-significant`: the profiles differ |
| 2 | bad input: argument, malformed stack/profile/plan/lens file, altered frame, refused output path |
| 3 | a device error or a lost link during `capture` (the folder is left resumable) |
| 4 | the machine: disk full, read-only file system, permission denied, out of memory, optional extra missing |
| 5 | internal error (a bug): a short message naming the command; `--debug` shows the traceback |
| 130 | interrupted (Ctrl-C); `capture` stops the stage and leaves a resumable folder |

No command writes through a symbolic link, over or into one of its inputs, or over an existing output without
`--overwrite`; every file appears whole or not at all; frames are checked against the sha256 stack.json records
(`--no-verify` skips it). The rules, and what each command writes, are in [safety.md](safety.md).

## The pipeline, as commands

A quick try on the simulated lens (the paper's uncorrected triplet), from the repository folder (it reads
`models/`), in about a minute. It renders at a small size, 320x180 px over the same 3840x2160 sensor area, so
the pixels are 19.6 µm and the Nyquist frequency is 25.5 cycles/mm: the target frequency is `--fs 10`
(0.4 x Nyquist) here, where the full-size sensor (1.63 µm pixels) takes the paper's `--fs 80`. A frequency at or
above 90 % of Nyquist is refused. `tests/test_docs_commands.py` runs this block as written.

```
fieldcal targets --out calibration_targets --dpi 100               # printable charts (PNG + PDF at a stated size)
fieldcal simulate models/triplet-uncorrected.json chart --z -370 60 20 --size 320x180   # a chart stack
fieldcal calibrate chart --out lens.json --fs 10 --q 0.05 --effort quick
fieldcal report lens.json --out report/
fieldcal profile show lens.json                                    # the profile in words (docs/profiles.md)
fieldcal profile export lens.json --format lensfun --out lens.xml --allow-no-distortion  # TCA only: texture shows no distortion
fieldcal plan stack lens.json --fs 10 --q 0.05 --confidence 0.95 --out plan.json --plots plan-plots/
fieldcal plan sweep lens.json --alpha-um 20 --pixel-exposure-ms 16 --device lcos --channels G --out sweep.json
fieldcal plan export-masks sweep.json --out sweep-masks            # the LCoS masks as 1-bit PNGs + masks.json
fieldcal plan sweep lens.json --alpha-um 20 --pixel-exposure-ms 10 --device pixel --out sweep-pixel.json
fieldcal plan export-masks sweep-pixel.json --out sweep-pixel-masks   # start/stop register maps (16-bit TIFF)
fieldcal capture --plan sweep-pixel.json --stage sim --camera sim:models/triplet-uncorrected.json,size=320x180,sub_step_um=5 --exposure-device sim:sweep-pixel-masks --out swept
fieldcal capture --plan plan.json --stage sim --camera sim:models/triplet-uncorrected.json,size=320x180 --out scene
fieldcal composite scene --profile lens.json --out image.tiff
fieldcal validate models/triplet-uncorrected.json --size 256x144 --effort quick --out validation/
fieldcal demo --out demo-out --size 320x180                         # all of the above, compared with the truth
```

The same at full size and on hardware (a PI stage on a serial port, a Basler camera; the simulated stage and
camera are `--stage sim --camera sim:LENS.json`). The frames of `--camera sim:...` are 320x180 unless its
`size=WxH` option says otherwise: a profile composites only stacks of its own image size.

<!-- docs-test: not run (needs a stage and a camera, or several minutes) -->
```
fieldcal targets --out calibration_targets                         # 300 dpi, A4 landscape
fieldcal capture --z -370 60 10 --stage gcs:/dev/ttyUSB0 --camera pylon --out chart
fieldcal calibrate chart --out lens.json --fs 80 --q 0.05 --effort standard --report report/
fieldcal plan stack lens.json --fs 80 --q 0.05 --confidence 0.95 --out plan.json --plots plan-plots/
fieldcal capture --plan plan.json --stage gcs:/dev/ttyUSB0 --camera pylon --out scene
fieldcal composite scene --profile lens.json --out image.tiff
fieldcal validate models/triplet-uncorrected.json --out validation/   # 640x360, standard effort: minutes
fieldcal demo --out demo-out                                          # 640x360
```

`fieldcal demo` prints each command before it runs it, so its log is a worked example. Every command's logic is
a public Python function (docs/architecture.md lists them); the commands only parse flags and print.

## Reference (generated)

Regenerate with `python -m fieldcal.commands._clidoc > docs/cli.md`.
"""


def main() -> None:
    os.environ.setdefault("COLUMNS", "110")
    from ..cli import build_parser
    parser = build_parser()
    out = io.StringIO()
    out.write(INTRO)
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, sub in subs.choices.items():
        out.write(f"\n### `fieldcal {name}`\n\n```\n{sub.format_help().rstrip()}\n```\n")
        nested = [a for a in sub._actions if isinstance(a, argparse._SubParsersAction)]
        for n in nested:
            for name2, sub2 in n.choices.items():
                out.write(f"\n#### `fieldcal {name} {name2}`\n\n```\n{sub2.format_help().rstrip()}\n```\n")
    print(out.getvalue(), end="")


if __name__ == "__main__":
    main()
