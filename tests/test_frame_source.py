"""One frame source: the on-disk Stack and the in-memory ArrayStack answer the same reading interface."""

import numpy as np
import pytest

import fieldcal.composite as composite
import fieldcal.measure as measure
from fieldcal.errors import ParameterError
from fieldcal.formats.frames import ArrayStack, FrameSource
from fieldcal.formats.stack import Stack, StackWriter


def _frames(n=3, h=12, w=16):
    rng = np.random.default_rng(0)
    return [rng.integers(0, 4096, (h, w, 3), dtype=np.uint16) for _ in range(n)]


def test_one_array_stack_for_measure_and_composite():
    assert measure.ArrayStack is composite.ArrayStack is ArrayStack


def test_array_stack_reads_like_the_file_stack(tmp_path):
    frames, z = _frames(), [20.0, -10.0, 5.0]
    w = StackWriter.create(tmp_path / "s", pixel_pitch_um=3.0, channels=["R", "G", "B"], white_level=4095)
    for f, zz in zip(frames, z):
        w.add_frame(f, zz)
    disk = Stack.open(tmp_path / "s")
    mem = ArrayStack(frames, z, ["R", "G", "B"], pixel_pitch_um=3.0, white_level=4095)
    for s in (disk, mem):
        assert isinstance(s, FrameSource)
    assert len(mem) == len(disk) and mem.shape == disk.shape and mem.dtype == disk.dtype
    assert mem.channels == disk.channels and mem.pixel_pitch_um == disk.pixel_pitch_um
    np.testing.assert_array_equal(mem.z_um, disk.z_um)
    np.testing.assert_array_equal(mem.order_by_z, disk.order_by_z)
    for roi in (None, (2, 3, 5, 4), (slice(1, 7), slice(0, 9))):
        for i in range(3):
            np.testing.assert_array_equal(mem.read(i, roi), disk.read(i, roi))
            np.testing.assert_array_equal(mem.read_normalized(i, roi), disk.read_normalized(i, roi))
    # the normalisation is (raw - black) / (white - black): a closed form
    np.testing.assert_allclose(mem.read_normalized(0), frames[0].astype(np.float32) / 4095, rtol=1e-6)


def test_lazy_frames_and_mosaic():
    calls = []

    def render(i):
        calls.append(i)
        return np.full((8, 10), float(i) / 4, np.float32)

    s = ArrayStack(render, [0.0, 1.0, 2.0], ["R", "G", "B"], cfa="RGGB", pixel_pitch_um=2.0)
    assert len(s) == 3 and s.shape == (8, 10) and s.read(2).shape == (8, 10)
    assert float(s.read_normalized(2)[0, 0]) == pytest.approx(0.5)
    with pytest.raises(ParameterError, match="odd"):
        s.read(0, (1, 0, 2, 2))


def test_errors_name_the_field():
    with pytest.raises(ParameterError, match="NaN"):
        ArrayStack([np.full((4, 4), np.nan, np.float32)], [0.0], ["Y"])
    with pytest.raises(ParameterError) as e:
        ArrayStack([np.zeros((4, 4))], [0.0], ["Y"]).read(3)
    assert e.value.field == "index"
    with pytest.raises(ParameterError) as e:
        ArrayStack([np.zeros((4, 4))] * 2, [0.0, 1.0], ["Y"]).require_frames(3, "a test")
    assert e.value.field == "frames"


def test_measurement_needs_a_pixel_pitch():
    from fieldcal.measure import measure_stack
    rng = np.random.default_rng(0)
    frames = [rng.random((64, 64)).astype(np.float32) for _ in range(7)]
    with pytest.raises(ParameterError) as e:
        measure_stack(ArrayStack(frames, np.arange(7.0) * 10, ["Y"]), fs_cyc_per_mm=40.0, quiet=True)
    assert e.value.field == "pixel_pitch_um"


@pytest.mark.parametrize("storage, scale, budget", [(np.uint16, 256.0, None), (np.uint16, 256.0, 0),
                                                    (np.uint16, 1.0, None), (np.float32, 1.0, 0)])
def test_held_frames_planes_are_what_read_returns(storage, scale, budget):
    """frame_planes on held frames (read, scaled and split in one pass) gives each channel exactly as
    ``HeldFrames.read`` does, from memory or the temporary file, over several bands; frames not held fall back."""
    from fieldcal.composite.dff import frame_planes
    from fieldcal.composite.source import HeldFrames

    rng = np.random.default_rng(5)
    h, w = 1100, 1000  # more than one band of rows (dff.BAND_BYTES)
    frames = [(rng.random((h, w, 3)) * 255).astype(np.uint8) for _ in range(2)]
    st = ArrayStack(frames, [0.0, 10.0], ["R", "G", "B"])
    held = HeldFrames(st, [1], storage, scale=scale, budget_bytes=budget)
    held.put(1, frames[1])
    assert held.in_memory == (budget is None)
    ref = held.read(1)
    got = frame_planes(held, None, 10.0, 1, ("R", "G", "B"), w, h)
    assert all(np.array_equal(got[c], ref[..., c].astype(np.float32)) for c in range(3))
    assert np.array_equal(frame_planes(held, None, 0.0, 0, ("R", "G", "B"), w, h)[2], frames[0][..., 2])


def test_composite_allocator_settings_take():
    """glibc accepts each malloc setting the composite command makes (a wrong parameter code is refused)."""
    import platform
    import subprocess
    import sys

    if not sys.platform.startswith("linux") or platform.libc_ver()[0] != "glibc":
        pytest.skip("glibc only")
    out = subprocess.run([sys.executable, "-c", "from fieldcal.composite.memory import tune_allocator; "
                          "print(tune_allocator())"], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "True"


def test_composite_turns_numpy_huge_pages_off():
    """tune_allocator leaves NumPy no longer asking for transparent huge pages (the switch reads back off)."""
    import subprocess
    import sys

    code = ("import numpy as np; from fieldcal.composite.memory import no_huge_pages, tune_allocator; "
            "core = getattr(np, '_core', None) or np.core; s = core.multiarray._set_madvise_hugepage; "
            "s(True); tune_allocator(); print(s(False)); s(True); print(no_huge_pages(), no_huge_pages())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "True", "False"]
