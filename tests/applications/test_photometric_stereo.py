"""Photometric stereo: exact shapes, weighted least squares, Frankot-Chellappa."""

from __future__ import annotations

import numpy as np
import pytest

from derender.applications.photometric_stereo import (
    angular_error_deg,
    bumps,
    default_lights,
    frankot_chellappa,
    read_lights,
    render_photometric_images,
    solve_normals,
    sphere,
)
from derender.camera.spectral import load_camera
from derender.core.errors import InputError


@pytest.mark.parametrize("make", [lambda: sphere(64), lambda: bumps(64, seed=1)])
def test_least_squares_recovers_exact_normals_from_linear_intensities(make):
    sc = make()
    L = default_lights(12, seed=2)
    shading = np.einsum("hwa,na->nhw", sc.normals, L)
    lit = np.all(shading > 0, axis=0) & sc.mask
    albedo = np.array([0.2, 0.5, 0.9])
    I = np.clip(shading, 0, None)[..., None] * albedo
    n, a = solve_normals(I, L, mask=sc.mask)
    assert angular_error_deg(n, sc.normals)[lit].max() < 1e-5
    np.testing.assert_allclose(a[lit], np.broadcast_to(albedo, a[lit].shape), rtol=1e-6)


def test_weights_downweight_corrupted_measurements():
    sc = sphere(48)
    L = default_lights(10, seed=0)
    I = np.clip(np.einsum("hwa,na->nhw", sc.normals, L), 0, None)[..., None] * np.ones(3)
    lit = np.all(np.einsum("hwa,na->nhw", sc.normals, L) > 0, axis=0) & sc.mask
    bad = I.copy()
    bad[0] *= 3.0                       # one wildly wrong image
    var = np.ones_like(I)
    var[0] = 1e6                         # ... that the model knows to be uncertain
    plain, _ = solve_normals(bad, L, mask=sc.mask)
    weighted, _ = solve_normals(bad, L, variances=var, mask=sc.mask)
    e_plain = angular_error_deg(plain, sc.normals)[lit].mean()
    e_weighted = angular_error_deg(weighted, sc.normals)[lit].mean()
    assert e_weighted < 0.05 < e_plain



def test_channel_clipped_in_every_image_does_not_dictate_the_normal():
    """Red clipped to a constant (bright albedo) in all images, known to be uncertain: the joint
    estimate follows the exact green and blue channels; the plain sum of pseudo-normals did not."""
    sc = bumps(48, seed=3)
    L = default_lights(12, seed=1)
    shading = np.einsum("hwa,na->nhw", sc.normals, L)
    lit = np.all(shading > 0, axis=0) & sc.mask
    I = np.clip(shading, 0, None)[..., None] * np.array([2.0, 0.5, 0.3])
    I[..., 0] = 1.0                     # red saturated everywhere
    var = np.full_like(I, 1e-4)
    var[..., 0] = 1.0                   # the model's variance for a clipped code
    n, a = solve_normals(I, L, variances=var, mask=sc.mask)
    assert angular_error_deg(n, sc.normals)[lit].max() < 0.5
    # the old rule (direction of the sum of the channels' pseudo-normals) is far off here
    b = [solve_normals(np.repeat(I[..., c:c + 1], 3, -1), L, mask=sc.mask) for c in range(3)]
    total = sum(bc[0] * bc[1][..., :1] for bc in b)
    old = total / np.maximum(np.linalg.norm(total, axis=-1, keepdims=True), 1e-300)
    assert angular_error_deg(old, sc.normals)[lit].mean() > 5.0

def test_frankot_chellappa_recovers_depth_up_to_offset():
    sc = bumps(96, seed=3)
    d = frankot_chellappa(sc.normals, sc.mask)
    assert np.corrcoef(d[sc.mask], sc.depth[sc.mask])[0, 1] > 0.99


def test_rendered_images_are_realistic():
    cam = load_camera("nikon-d5100")
    sc = sphere(48)
    L = default_lights(6)
    codes, raw, m, wb = render_photometric_images(sc, cam, L, seed=0)
    assert codes.shape == (6, 48, 48, 3) and codes.dtype == np.uint8
    assert (codes == 255).any() and raw.max() == pytest.approx(1.6)
    # gamma-2.2 inversion of the JPEGs is far from the linear truth
    lit = np.all(np.einsum("hwa,na->nhw", sc.normals, L) > 0, axis=0) & sc.mask
    n, _ = solve_normals((codes / 255.0) ** 2.2, L, mask=sc.mask)
    assert angular_error_deg(n, sc.normals)[lit].mean() > 3.0


def test_read_lights(tmp_path):
    f = tmp_path / "l.txt"
    f.write_text("0 0 1\n0 1 1 2\n1, 0, 1\n")
    L = read_lights(f)
    np.testing.assert_allclose(np.linalg.norm(L, axis=1), [1, 2, 1])
    f.write_text("0 0 1\n")
    with pytest.raises(InputError, match="at least 3"):
        read_lights(f)
    f.write_text("0 0 x\n")
    with pytest.raises(InputError):
        read_lights(f)
