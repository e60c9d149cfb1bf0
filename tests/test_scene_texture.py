"""The simulator's dead-leaves chart is isotropic at the focus measure's frequencies (an astigmatic lens's texture
focus sits at the mean of T and S only for a chart with equal energy along both)."""
import numpy as np

from fieldcal.simulate.scene import load_scene, sensor_texture


def _x_share(img: np.ndarray, f0: float, half_width: float = 0.03) -> float:
    """Fraction of the ring |f| = f0 (cycles/px) power along x (cos^2 weighting; 0.5 for an isotropic image)."""
    img = np.asarray(img, np.float64)
    power = np.abs(np.fft.fft2(img - img.mean())) ** 2
    fy = np.fft.fftfreq(img.shape[0])[:, None]
    fx = np.fft.fftfreq(img.shape[1])[None, :]
    f = np.hypot(fx, fy)
    ring = (f > f0 - half_width) & (f < f0 + half_width)
    cos2 = np.broadcast_to(fx * fx, f.shape)[ring] / f[ring] ** 2
    p = power[ring]
    return float(np.sum(p * cos2) / np.sum(p))


def test_chart_texture_is_isotropic_at_high_frequency():
    img, name = load_scene("chart", 384, 384, seed=3)
    assert name == "chart" and img.dtype == np.float32 and img.shape == (384, 384)
    for f0 in (0.2, 0.3, 0.4):
        # the 1-sigma spread of a ring's share on a 384^2 dead-leaves image is ~0.01
        assert abs(_x_share(img, f0) - 0.5) < 0.03, f0


def test_sensor_texture_range_and_memory_cap(monkeypatch):
    img = sensor_texture(96, 64, seed=1)
    assert img.shape == (64, 96) and 0.1 - 1 / 255 <= img.min() and img.max() <= 0.9 + 1 / 255
    assert abs(float(img.mean()) - 0.5) < 0.1
    import fieldcal.simulate.scene as scene
    monkeypatch.setattr(scene, "MAX_DRAWN_PX", 96 * 64)  # no room to oversample: drawn at the sensor size
    from fieldcal.charts.targets import random_texture
    np.testing.assert_array_equal(scene.sensor_texture(96, 64, seed=1), random_texture(96, 64, seed=1))
