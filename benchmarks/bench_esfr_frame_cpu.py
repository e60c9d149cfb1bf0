"""Per-frame CPU of the slanted-edge measurement: edge detection (``find_edges``) and the batched e-SFR
(``esfr_regions``) on frames of a stack, in this process, BLAS and OpenCV on one thread (as in a worker of
``fieldcal/measure/esfr_pool.py``).

``PYTHONPATH`` selects the tree measured, so two trees are compared by running this twice, each with ``--dump``,
then ``--compare``: the largest |difference| of every per-edge output (raw MTF, MTF50, position, angle, each
quality figure) and of the stored 5-decimal MTF records, with the edges and their quality reasons required equal.

    cd /tmp && PYTHONPATH=TREE python TREE/benchmarks/bench_esfr_frame_cpu.py STACK --frames 0,20,40 --dump a.pkl
    python benchmarks/bench_esfr_frame_cpu.py --compare a.pkl b.pkl
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import pickle  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402


def measure(stack_path: str, frames: list[int], reps: int) -> tuple[dict, dict]:
    import cv2

    import fieldcal
    from fieldcal.formats.stack import Stack
    from fieldcal.measure import mtf as M
    from fieldcal.measure.esfr import esfr_regions
    from fieldcal.measure.esfr_detect import find_edges
    try:
        from fieldcal._numeric import channel_mean
    except ImportError:  # a tree before session 19 (the benchmark compares two)
        channel_mean = M._plane_mean
    cv2.setNumThreads(1)
    st = Stack.open(stack_path, verify=False)
    channels = tuple(st.channels)
    if getattr(st, "cfa", None):
        raise SystemExit("error: a mosaic (CFA) stack; this benchmark takes demosaiced frames")
    out, cpu = {}, {"find_edges": 0.0, "esfr": 0.0, "measure_frame": 0.0}
    for rep in range(reps):
        for k in frames:
            img = st.read_normalized(k)
            planes, _ = M._plane_stack(img, channels, None)
            t0 = time.process_time()
            cands = find_edges(channel_mean(planes))
            t1 = time.process_time()
            res = esfr_regions([planes[c.roi[0]:c.roi[1], c.roi[2]:c.roi[3], :] for c in cands],
                               vertical=[c.vertical for c in cands], line_init=[c.line_init for c in cands],
                               half_width_px=[c.half_width_px for c in cands])
            t2 = time.process_time()
            recs, _ = M.measure_frame(img, channels=channels, frame_index=k)
            t3 = time.process_time()
            cpu["find_edges"] += t1 - t0
            cpu["esfr"] += t2 - t1
            cpu["measure_frame"] += t3 - t2
            if rep == 0:
                out[k] = {"cands": [(c.x_px, c.y_px, c.angle_deg, c.length_px, c.vertical, c.roi, c.line_init,
                                     c.half_width_px) for c in cands],
                          "res": [(r.mtf, r.mtf50_cy_per_px, r.x_mid, r.y_mid, r.angle_deg,
                                   [q.to_dict() for q in r.quality]) for r in res],
                          "recs": [x["mtf"] for x in recs]}
    n = reps * len(frames)
    summary = {"tree": os.path.dirname(os.path.dirname(fieldcal.__file__)), "frames": len(frames), "reps": reps,
               "edges_per_frame": float(np.mean([len(o["cands"]) for o in out.values()])),
               **{f"{k}_ms": 1e3 * v / n for k, v in cpu.items()}}
    return out, summary


def compare(a: dict, b: dict) -> dict:
    """Largest |difference| per output; raises AssertionError if the edges or quality reasons differ."""
    worst: dict = {}

    def upd(key, x, y):
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        fx, fy = np.isfinite(x), np.isfinite(y)
        assert np.array_equal(fx, fy), f"{key}: NaN in one tree only"
        if fx.any():
            worst[key] = max(worst.get(key, 0.0), float(np.abs(x[fx] - y[fx]).max()))

    assert sorted(a) == sorted(b), "different frames"
    for k in a:
        A, B = a[k], b[k]
        assert len(A["cands"]) == len(B["cands"]), f"frame {k}: {len(A['cands'])} vs {len(B['cands'])} edges"
        for ca, cb in zip(A["cands"], B["cands"]):
            assert ca[4] == cb[4] and ca[5] == cb[5], f"frame {k}: edge regions differ {ca[5]} {cb[5]}"
            upd("detection x, y, angle, length", ca[:4], cb[:4])
            upd("detection line_init", ca[6], cb[6])
            upd("detection half_width_px", ca[7], cb[7])
        for ra, rb in zip(A["res"], B["res"]):
            for i, name in enumerate(("mtf", "mtf50_cy_per_px", "x_mid", "y_mid", "angle_deg")):
                upd(name, ra[i], rb[i])
            for qa, qb in zip(ra[5], rb[5]):
                assert qa["reason"] == qb["reason"], (qa["reason"], qb["reason"])
                for key, v in qa.items():
                    if key not in ("reason", "ok"):
                        upd("quality." + key, v, qb[key])
        for x, y in zip(A["recs"], B["recs"]):
            upd("record mtf (5 decimals)", x, y)
    return worst


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("stack", nargs="?", help="a fieldcal-stack/1 folder of demosaiced slanted-edge frames")
    ap.add_argument("--frames", default="0", help="comma-separated frame indices (file order), or 'all'")
    ap.add_argument("--reps", type=int, default=3, help="passes over the frames (CPU is averaged)")
    ap.add_argument("--dump", help="save the per-edge outputs here (for --compare)")
    ap.add_argument("--compare", nargs=2, metavar=("A", "B"), help="compare two --dump files")
    args = ap.parse_args(argv)
    if args.compare:
        a, b = (pickle.load(open(p, "rb")) for p in args.compare)
        for key, v in compare(a, b).items():
            print(f"max |diff| {key}: {v:.3g}")
        print(f"edges and quality reasons equal in {sum(len(f['cands']) for f in a.values())} edges")
        return 0
    if not args.stack:
        ap.error("give a stack folder (or --compare A B)")
    if args.frames == "all":
        from fieldcal.formats.stack import Stack
        frames = list(range(len(Stack.open(args.stack, verify=False))))
    else:
        frames = [int(v) for v in args.frames.split(",")]
    out, s = measure(args.stack, frames, max(1, args.reps))
    print(f"{s['tree']}: {s['frames']} frames x {s['reps']}, {s['edges_per_frame']:.0f} edges a frame; CPU a frame: "
          f"find_edges {s['find_edges_ms']:.1f} ms, esfr_regions {s['esfr_ms']:.1f} ms, "
          f"measure_frame (both + records) {s['measure_frame_ms']:.1f} ms")
    if args.dump:
        with open(args.dump, "wb") as f:
            pickle.dump(out, f)
    return 0


if __name__ == "__main__":
    sys.exit(main())
