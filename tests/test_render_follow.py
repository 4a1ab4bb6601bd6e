"""Gaussians following particles: interpolation, F Sigma0 F^T, gradients to x and F, 3DGS covariances."""

import pytest
import torch

from gca.render import Binding, BindingError, covariance_from_scale_rot, follow, quat_to_rotmat, smallest_axis_normal

F64 = torch.float64


def _binding(G: int = 5, P: int = 7, seed: int = 0) -> Binding:
    """Each Gaussian bound to 2-3 random particles with random weights summing to 1."""
    g = torch.Generator().manual_seed(seed)
    rows, cols, weights = [], [], []
    for k in range(G):
        n = 2 + k % 2
        p = torch.randperm(P, generator=g)[:n]
        w = torch.rand(n, generator=g, dtype=F64) + 0.1
        rows += [k] * n
        cols += p.tolist()
        weights.append(w / w.sum())
    return Binding(rows=torch.tensor(rows), cols=torch.tensor(cols), weights=torch.cat(weights),
                   n_gaussians=G, n_particles=P)


def _state(G: int = 5, P: int = 7, seed: int = 1):
    g = torch.Generator().manual_seed(seed)
    means0 = torch.rand(G, 3, generator=g, dtype=F64)
    A = 0.1 * torch.randn(G, 3, 3, generator=g, dtype=F64)
    covs0 = A @ A.transpose(1, 2)
    x0 = torch.rand(P, 3, generator=g, dtype=F64)
    x = x0 + 0.05 * torch.randn(P, 3, generator=g, dtype=F64)
    F = torch.eye(3, dtype=F64) + 0.1 * torch.randn(P, 3, 3, generator=g, dtype=F64)
    return means0, covs0, x0, x, F


def test_matches_dense_matrix_formula():
    binding = _binding()
    means0, covs0, x0, x, F = _state()
    means, covs = follow(binding, means0, covs0, x0, x, F)
    W = binding.to_sparse().to_dense()
    F_g = torch.einsum("gp,pij->gij", W, F)
    torch.testing.assert_close(means, means0 + W @ (x - x0))
    torch.testing.assert_close(covs, F_g @ covs0 @ F_g.transpose(1, 2))


def test_rigid_motion_translates_and_rotates():
    binding = _binding()
    means0, covs0, x0, _, _ = _state()
    R = quat_to_rotmat(torch.tensor([[0.9, 0.1, -0.3, 0.2]], dtype=F64))[0]
    t = torch.tensor([0.1, -0.2, 0.3], dtype=F64)
    centre = x0.mean(0)
    x = (x0 - centre) @ R.T + centre + t
    F = R.expand(7, 3, 3)
    means, covs = follow(binding, means0, covs0, x0, x, F)
    torch.testing.assert_close(covs, R @ covs0 @ R.T)
    # rows sum to 1, so W (x - x0) of an affine motion is the motion of the interpolated rest point
    W = binding.to_sparse().to_dense()
    torch.testing.assert_close(means - means0, (W @ x0 - centre) @ R.T + centre + t - W @ x0)


@pytest.mark.grad
def test_gradients_reach_x_and_F():
    binding = _binding()
    means0, covs0, x0, x, F = _state()
    x, F = x.clone().requires_grad_(), F.clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda x_, F_: follow(binding, means0, covs0, x0, x_, F_), (x, F))
    means, covs = follow(binding, means0, covs0, x0, x, F)
    v_x, v_F = torch.autograd.grad(means.sum() + covs.square().sum(), (x, F))
    assert v_x.abs().sum() > 0 and v_F.abs().sum() > 0    # the covariance path is not cut (NeuMA cut it)


def _nodes(t: torch.Tensor) -> set[str]:
    """The names of the autograd nodes behind ``t``."""
    seen, todo = set(), [t.grad_fn]
    while todo:
        f = todo.pop()
        if f is not None and type(f).__name__ not in seen:
            seen.add(type(f).__name__)
            todo += [g for g, _ in f.next_functions]
    return seen


def test_apply_gathers_by_index_select_and_equals_the_indexing_it_replaced():
    """The gather's backward is index_select's (an index_add), not advanced indexing's sort-based index_put_; the
    values are the indexing's bitwise and the gradient equal to float64 rounding (the profile's 6.5 ms an iteration)."""
    binding = _binding(G=40, P=25, seed=3)
    _, _, _, x, F = _state(G=40, P=25, seed=4)
    x = x.clone().requires_grad_()
    out = binding.apply(F.reshape(25, 9) * x[:, :1])
    names = _nodes(out)
    assert "IndexSelectBackward0" in names and "IndexBackward0" not in names
    w = binding.weights.reshape(-1, 1)
    x2 = x.detach().clone().requires_grad_()
    old = torch.zeros(40, 9, dtype=F64).index_add(0, binding.rows, w * (F.reshape(25, 9) * x2[:, :1])[binding.cols])
    assert "IndexBackward0" in _nodes(old)  # the control: the indexing it replaced
    assert torch.equal(out, old)
    g = torch.randn(40, 9, dtype=F64, generator=torch.Generator().manual_seed(5))
    torch.testing.assert_close(torch.autograd.grad(out, x, g)[0], torch.autograd.grad(old, x2, g)[0],
                               rtol=1e-14, atol=1e-15)


def test_binding_validation_and_sparse_round_trip():
    binding = _binding()
    back = Binding.from_sparse(binding.to_sparse())
    torch.testing.assert_close(back.to_sparse().to_dense(), binding.to_sparse().to_dense())
    with pytest.raises(BindingError, match="sum to 1"):
        Binding(rows=torch.tensor([0, 1]), cols=torch.tensor([0, 1]), weights=torch.tensor([1.0, 0.5]),
                n_gaussians=2, n_particles=2)
    with pytest.raises(BindingError, match="sum to 1"):   # Gaussian 1 has no particle
        Binding(rows=torch.tensor([0]), cols=torch.tensor([0]), weights=torch.tensor([1.0]),
                n_gaussians=2, n_particles=2)
    with pytest.raises(BindingError, match="particle indices"):
        Binding(rows=torch.tensor([0]), cols=torch.tensor([5]), weights=torch.tensor([1.0]),
                n_gaussians=1, n_particles=2)


def test_covariance_from_scale_rot_and_smallest_axis():
    log_scales = torch.log(torch.tensor([[0.3, 0.2, 0.01], [0.05, 0.5, 0.4]], dtype=F64))
    quats = torch.tensor([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 2.0]], dtype=F64)  # identity; 180 deg about z
    covs = covariance_from_scale_rot(log_scales, quats)
    torch.testing.assert_close(covs[0], torch.diag(torch.tensor([0.09, 0.04, 1e-4], dtype=F64)))
    torch.testing.assert_close(covs[1], torch.diag(torch.tensor([0.0025, 0.25, 0.16], dtype=F64)))
    normals = smallest_axis_normal(covs)
    torch.testing.assert_close(normals.abs(), torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], dtype=F64))
    R = quat_to_rotmat(torch.tensor([[0.8, 0.2, 0.5, -0.1]], dtype=F64)).expand(2, 3, 3)
    rotated = smallest_axis_normal(R @ covs @ R.transpose(1, 2))
    torch.testing.assert_close((rotated * (R @ normals[..., None])[..., 0]).sum(-1).abs(), torch.ones(2, dtype=F64))


def test_frames_at_once_equal_each_frame():
    """follow on T states at once (x [T, P, 3], F [T, P, 3, 3]: a training iteration's frames, session 40) equals
    follow frame by frame, values and gradients to each frame's x and F; a frame count that differs between x and F
    is refused."""
    binding = _binding()
    means0, covs0, x0, _, _ = _state()
    g = torch.Generator().manual_seed(5)
    xs = (x0 + 0.05 * torch.randn(3, *x0.shape, generator=g, dtype=F64)).requires_grad_()
    Fs = (torch.eye(3, dtype=F64) + 0.1 * torch.randn(3, x0.shape[0], 3, 3, generator=g, dtype=F64)).requires_grad_()
    means, covs = follow(binding, means0, covs0, x0, xs, Fs)
    assert means.shape == (3, 5, 3) and covs.shape == (3, 5, 3, 3)
    w_m, w_c = torch.randn(means.shape, generator=g, dtype=F64), torch.randn(covs.shape, generator=g, dtype=F64)
    g_x, g_F = torch.autograd.grad((means * w_m).sum() + (covs * w_c).sum(), (xs, Fs))
    for t in range(3):
        x, F = xs[t].detach().requires_grad_(), Fs[t].detach().requires_grad_()
        m, c = follow(binding, means0, covs0, x0, x, F)
        torch.testing.assert_close(means[t], m)
        torch.testing.assert_close(covs[t], c)
        r_x, r_F = torch.autograd.grad((m * w_m[t]).sum() + (c * w_c[t]).sum(), (x, F))
        torch.testing.assert_close(g_x[t], r_x)
        torch.testing.assert_close(g_F[t], r_F)
    with pytest.raises(AssertionError, match="x0/x/F"):
        follow(binding, means0, covs0, x0, xs, Fs[:2])
