"""Big stacks (issue 15): compositing memory does not grow with the number of frames, registered frames streamed
from the temporary file give the in-memory composite, the memory and temporary-disk checks refuse clearly, support
masks held as bits are the masks, and long phases report progress. Small images: the checks are on behaviour."""

import errno
import tracemalloc

import numpy as np
import pytest

from fieldcal.composite import memory
from fieldcal.composite import register as R
from fieldcal.composite import source
from fieldcal.errors import ParameterError, ResourceError
from fieldcal.formats.frames import ArrayStack

W, H = 160, 120


def _scene_stack(n, seed=0, size=(W, H)):
    """``n`` frames of a textured scene whose left half is sharp early and right half late (a scene with depth),
    8-bit RGB like a camera's JPEGs, ``size`` = (W, H)."""
    import cv2

    W, H = size
    rng = np.random.default_rng(seed)
    tex = cv2.GaussianBlur(rng.random((H, W)).astype(np.float32), (0, 0), 1.0)
    tex = (tex - tex.mean()) / tex.std() * 0.15 + 0.5
    frames = []
    for k in range(n):
        t = k / max(n - 1, 1)
        out = np.empty_like(tex)
        for sl, best in ((np.s_[:, :W // 2], 0.25), (np.s_[:, W // 2:], 0.75)):
            s = 3.0 * abs(t - best)
            out[sl] = (cv2.GaussianBlur(tex, (0, 0), s) if s > 0.05 else tex)[sl]
        f = np.repeat(out[..., None], 3, axis=2) * np.array([1.0, 0.9, 0.8], np.float32)
        frames.append(np.clip(np.rint(f * 255), 0, 255).astype(np.uint8))
    return ArrayStack(frames, np.arange(n) * 10.0, ["R", "G", "B"])


def _peak_bytes(fn):
    tracemalloc.start()
    try:
        fn()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_composite_memory_does_not_grow_with_frames(monkeypatch):
    """With the registered frames streamed from the temporary file (as any big stack's are), 16 frames peak
    where 4 do, but for what registration must keep per frame: its grey registration plane (float32, at most
    1024 px on the long side). The composite holds a few frames' planes, never the stack: holding its frames
    as float32 would add 12 x 230 kB, and registration holding every pair's pyramid (as it did) 12 x 0.7 MB."""
    from fieldcal.composite.api import composite_stack

    monkeypatch.setattr(source, "MEMORY_BUDGET_BYTES", 0)
    w, h = 2 * W, 2 * H  # per-frame costs well above the run's fixed allocations (caches, first-use imports)
    composite_stack(_scene_stack(3, size=(w, h)), depth="3d", quiet=True)  # first-use allocations not counted
    peaks = {n: _peak_bytes(lambda n=n: composite_stack(_scene_stack(n, size=(w, h)), depth="3d", quiet=True))
             for n in (4, 16)}
    frame_f32 = w * h * 3 * 4
    # per extra frame: the stack itself (an in-memory ArrayStack of uint8, made inside) and a registration plane
    per_frame = w * h * 3 + w * h * 4
    assert peaks[16] - peaks[4] < 12 * per_frame + 2 * frame_f32, peaks


def test_streamed_registered_frames_give_the_in_memory_composite(monkeypatch):
    from fieldcal.composite.api import composite_stack

    st = _scene_stack(5, seed=3)
    held = composite_stack(st, depth="3d", quiet=True).image
    monkeypatch.setattr(source, "MEMORY_BUDGET_BYTES", 0)
    streamed = composite_stack(st, depth="3d", quiet=True).image
    np.testing.assert_array_equal(streamed, held)


def test_memory_check_refuses_before_any_work_and_says_what_fits(monkeypatch):
    from fieldcal.composite.api import composite_stack

    calls = []
    monkeypatch.setattr(R, "register_stack", lambda *a, **k: calls.append(1))  # nothing may start
    with pytest.raises(ResourceError) as e:
        composite_stack(_scene_stack(3), max_memory="1M", quiet=True)
    assert not calls and e.value.field == "max_memory" and "fit" in str(e.value)
    # the size it says fits does fit: its estimate is within the limit, with the headroom
    limit = memory.BASE_BYTES + memory.BYTES_PER_SAMPLE * 4000 * 3000 * 3
    with pytest.raises(ResourceError) as e:
        memory.check_memory(6000, 4000, 3, 60, max_memory_bytes=int(limit))
    w, h = (int(v) for v in str(e.value).split("up to about ")[1].split(" px")[0].split("x"))
    assert memory.estimate_peak_bytes(w, h, 3) * memory.HEADROOM <= limit
    assert memory.estimate_peak_bytes(w + 8, h + 8, 3) * memory.HEADROOM > limit * 0.98
    assert memory.check_memory(160, 120, 3, 5, max_memory_bytes=2 ** 40)["estimated_peak_bytes"] > 0


def test_memory_sizes_parse_with_units():
    assert memory.parse_memory_bytes("8G") == 8 * 2 ** 30
    assert memory.parse_memory_bytes("512 MiB") == 512 * 2 ** 20
    assert memory.parse_memory_bytes(1e9) == 10 ** 9
    assert memory.parse_memory_bytes(None) is None
    for bad in ("lots", "-1G", 0, "G"):
        with pytest.raises(ParameterError):
            memory.parse_memory_bytes(bad)


def test_available_memory_is_positive_where_the_kernel_says():
    avail = memory.available_memory_bytes()
    assert avail is None or avail > 0


def test_temporary_disk_is_checked_before_frames_are_held(monkeypatch):
    import shutil
    from collections import namedtuple

    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: usage(10 ** 6, 10 ** 6 - 1000, 1000))
    st = _scene_stack(3)
    with pytest.raises(ResourceError) as e:
        source.HeldFrames(st, [0, 1, 2], np.uint16, budget_bytes=0)
    assert e.value.field == "TMPDIR" and "TMPDIR" in e.value.fix
    monkeypatch.setattr(source, "MEMORY_BUDGET_BYTES", 0)
    with pytest.raises(ResourceError):
        R.register_stack(st, quiet=True)


def test_disk_full_while_holding_frames_is_a_resource_error(monkeypatch):
    held = source.HeldFrames(_scene_stack(2), [0, 1], np.uint8, budget_bytes=0)

    def full(*a):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(source.os, "pwrite", full)
    with pytest.raises(ResourceError) as e:
        held.put(0, np.zeros((H, W, 3), np.uint8))
    assert "TMPDIR" in e.value.fix


def test_support_masks_held_as_bits_are_the_frames_recorded_area():
    """A frame magnified 4 % about the centre shows less than the reference: its mask is False exactly where the
    output pixel maps outside the frame (beyond the warp's margin), to the rounding of a pixel."""
    geo = R.EstimatedGeometry(0.0, ((W - 1) / 2, (H - 1) / 2), 0.04 / 10.0, (0.0, 0.0), 1)
    sup = R.FrameSupport(geo, {0: 0.0, 1: 10.0}, W, H)
    assert sup(0) is None  # the reference covers everything
    mask = sup(1)
    assert mask.dtype == bool and mask.shape == (H, W)
    assert sup._masks[1].nbytes <= W * H // 8 + 1  # held packed
    np.testing.assert_array_equal(sup(1), mask)
    m = R.frame_map_matrix(geo, 10.0)
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    qx, qy = R._apply(m, xx.ravel(), yy.ravel())
    mg = R.SUPPORT_MARGIN_PX
    inside = ((qx >= mg - 0.5) & (qx < W - mg - 0.5) & (qy >= mg - 0.5) & (qy < H - mg - 0.5)).reshape(H, W)
    inner = (slice(mg, H - mg), slice(mg, W - mg))
    # disagreement only on the boundary ring (a pixel's rounding)
    near = np.abs(qx - np.clip(qx, mg - 0.5, W - mg - 0.5)).reshape(H, W) + \
        np.abs(qy - np.clip(qy, mg - 0.5, H - mg - 0.5)).reshape(H, W)
    differ = (mask != inside)[inner]
    assert not np.any(differ & (near[inner] > 1.0))
    assert 0.85 < mask.mean() < 0.95  # 1/1.04^2 of the area


def test_registration_reports_progress_on_every_long_phase(monkeypatch, capsys):
    monkeypatch.setenv("FIELDCAL_PROGRESS", "1")
    monkeypatch.setattr(source, "roi_readable", lambda stack, i: False)  # as JPEG frames: decoded and held
    R.register_stack(_scene_stack(4), quiet=False)
    err = capsys.readouterr().err
    for phase in ("reading", "registering", "choosing the model", "warping"):
        assert phase in err, phase


def test_cli_refuses_a_composite_beyond_max_memory_with_exit_4_and_the_flag(tmp_path, capsys):
    import cv2

    from fieldcal.cli import main
    from fieldcal.errors import EXIT_ENVIRONMENT
    from fieldcal.formats.importer import import_stack

    st = _scene_stack(3)
    files = []
    for k in range(3):
        files.append(tmp_path / f"f{k}.png")
        cv2.imwrite(str(files[-1]), st.read(k)[..., ::-1])
    import_stack(files, tmp_path / "st", z_start_um=0.0, z_step_um=10.0, pixel_pitch_um=2.0)
    out = tmp_path / "out.tiff"
    code = main(["composite", str(tmp_path / "st"), "--out", str(out), "--max-memory", "1M", "--quiet"])
    err = capsys.readouterr().err
    assert code == EXIT_ENVIRONMENT and not out.exists()
    assert "--max-memory" in err and "fix:" in err and "Traceback" not in err
    assert main(["composite", str(tmp_path / "st"), "--out", str(out), "--max-memory", "lots", "--quiet"]) == 2


def test_available_memory_check_counts_only_what_the_images_add(monkeypatch):
    """The memory available now excludes the interpreter the process already holds: a small composite passes
    with a little more than its images' part free, and is refused with less."""
    images = memory.estimate_peak_bytes(2048, 1536, 3) - memory.BASE_BYTES
    monkeypatch.setattr(memory, "available_memory_bytes", lambda: int(images * memory.HEADROOM) + 1)
    memory.check_memory(2048, 1536, 3, 10)
    monkeypatch.setattr(memory, "available_memory_bytes", lambda: int(images * 0.9))
    with pytest.raises(ResourceError) as e:
        memory.check_memory(2048, 1536, 3, 10)
    assert "available now" in str(e.value)


def test_fine_detail_takes_a_frame_beyond_the_255th():
    """A 300-frame stack (a deep macro stack on a rail): the sharp frame is number 280; the per-coefficient choice
    is held in 16 bits, so it is that frame's detail that is taken (8 bits would wrap it to frame 24)."""
    import cv2

    from fieldcal.composite.detail import fine_detail

    rng = np.random.default_rng(7)
    sharp = rng.random((32, 32, 1)).astype(np.float32)
    soft = cv2.GaussianBlur(sharp, (0, 0), 2.0)[..., None]
    n, k = 300, 280
    frames = [sharp if j == k else soft for j in range(n)]
    st = ArrayStack(frames, np.arange(n) * 5.0, ["Y"])
    out, info = fine_detail(st, soft, np.full((32, 32), float(k), np.float32), quiet=True)
    assert np.abs(out - sharp).mean() < 0.3 * np.abs(soft - sharp).mean()
