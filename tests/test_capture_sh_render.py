"""A scan's SH bands 1-3 reach the renderer: view-dependent colour through gca.scenes.world."""

from __future__ import annotations

import torch

from gca.assets import particles as pa
from gca.assets.ply import write_ply
from gca.assets.testscan import torus_scan
from gca.render.camera import look_at
from gca.sh import view_term
from gca.scenes import world


def _body(tmp_path, degree):
    cloud = torus_scan(n=1500, sh_degree=degree, seed=3)
    write_ply(tmp_path / "g.ply", cloud)
    pa.save_particles(tmp_path / "p.npz", pa.convert(cloud, pa.ParticleConfig(spacing=0.02), density=1000.0))
    return world.load_body(tmp_path / "p.npz", tmp_path / "g.ply")


def test_sh_bands_make_colour_view_dependent(tmp_path):
    body = _body(tmp_path, 1)
    assert body.sh_rest is not None and body.sh_rest.shape == (body.n_gaussians, 3, 3)
    front = look_at([0.5, 1.5, 1.5], [0.5, 0.1, 0.5], [0, -1, 0], 40.0, 32, 32)
    back = look_at([0.5, -1.2, 1.5], [0.5, 0.1, 0.5], [0, -1, 0], 40.0, 32, 32)
    a, b = world.body_colors(body, body.means0, front), world.body_colors(body, body.means0, back)
    assert (a - b).abs().max() > 0.1  # the band-1 tint (along y) differs seen from above and below
    centre = torch.as_tensor(front.center, dtype=body.means0.dtype)
    torch.testing.assert_close(a, (body.colors + view_term(body.sh_rest, body.means0, centre)).clamp(0, 1))
    bg = torch.zeros(3)
    seen = world.render_gaussians(body, body.means0, body.covs0, body.colors, front, bg)["rgb"]
    flat = world.render_gaussians(body, body.means0, body.covs0, body.colors.clone(), front, bg)["rgb"]
    assert (seen - flat).abs().max() > 0.02  # body.colors itself means "the scan's colours, SH included"


def test_degree_zero_scan_keeps_flat_colours(tmp_path):
    body = _body(tmp_path, 0)
    cam = look_at([0.5, 0.3, 2.0], [0.5, 0.1, 0.5], [0, -1, 0], 40.0, 32, 32)
    assert body.sh_rest is None and world.body_colors(body, body.means0, cam) is body.colors


def test_view_term_of_frames_at_once_equals_each_frame():
    """view_term on T frames' means [T, G, 3] (a training iteration's frames rendered at once, session 40) equals
    each frame's [G, 3] call, for every SH degree; degree 0 gives zeros of the frames' shape."""
    g = torch.Generator().manual_seed(0)
    means = torch.rand(4, 9, 3, generator=g, dtype=torch.float64)
    centre = torch.tensor([0.3, -1.0, 2.0], dtype=torch.float64)
    for K in (3, 8, 15):
        sh_rest = torch.randn(9, K, 3, generator=g, dtype=torch.float64)
        frames = view_term(sh_rest, means, centre)
        assert frames.shape == (4, 9, 3)
        for t in range(4):
            torch.testing.assert_close(frames[t], view_term(sh_rest, means[t], centre))
    assert view_term(torch.zeros(9, 0, 3, dtype=torch.float64), means, centre).shape == (4, 9, 3)
