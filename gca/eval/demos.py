"""Generalization demos: a learned law on a new shape, and two learned laws meeting in one simulation.

Three demos show what a law learned from one video can do beyond its training scene:

- **new shape**: the law learned on scene ``law_scene`` (e.g. the gel duck) drives another object's
  particles (e.g. the ball), launched with a chosen velocity;
- **interaction**: two objects, each driven by the law learned on its own scene, are placed side by
  side (or stacked) in ONE MLS-MPM simulation, launched towards each other; the grid couples them;
- **capture** (``demo.captures.<scene>``): the law learned on a capture scene (the user's video) drives its
  object raised, turned (:func:`place_body`) and thrown anew, filmed by the capture's own camera over its plate
  at the video's frame rate (:func:`run_capture_demo`).

Both are simulated without gradients, rendered from an orbit camera (optionally sweeping in
azimuth) to an animated GIF and a frame strip PNG, and summarised by metrics a user can check at a
glance: frames simulated, whether the state stayed finite, the drop of the centre of mass, and the
largest principal strain ``max |sigma - 1|`` over particles and frames (per object).

Combining two objects. Both bodies are mapped by one similarity ``x -> s x + t`` each (a common
scale ``s <= 1`` so that the pair fits the unit cube with a gap between them; volumes and masses
scale by ``s^3`` so the density is kept, covariances by ``s^2``), then concatenated: particles
``[P_a + P_b]`` (a first), Gaussians ``[G_a + G_b]`` with the binding's indices of ``b`` offset by
``(G_a, P_a)``. The laws are combined with :class:`gca.laws.base.CompositeMaterial` over the two
contiguous particle ranges.

Laws. The simulation functions take materials (any :class:`gca.laws.base.Material`), so tests and
users can pass analytic laws; :func:`load_demo_law` rebuilds a trained law from the pipeline's
``runs/<scene>/<method>/law.pt``. A missing trained law falls back to the scene's neural prior with
a ``RuntimeWarning`` (``missing_law: prior``, the default) or raises ``FileNotFoundError``
(``missing_law: error``); the metrics record which law was used (``law_source``).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from pathlib import Path
from typing import Mapping, Sequence

import imageio.v3 as iio
import numpy as np
import torch

from gca import config
from gca.io import atomic_path
from gca.laws.base import CompositeMaterial, Material
from gca.render.camera import Camera
from gca.render.follow import Binding
from gca.scenes.config import OrbitCamera
from gca.scenes.ground_truth import make_camera
from gca.scenes.world import Body, initial_velocity, render_body
from gca.sim.rollout import Rollout, SimulationDiverged, rollout
from gca.sim.solver import MPMSolver

_WHERE = "gca/eval/demos.py"
LAYOUTS = ("side_by_side", "stacked")
MISSING_LAW = ("prior", "error")


def _vec3(value, name: str) -> tuple[float, float, float]:
    out = tuple(float(v) for v in value)
    if len(out) != 3 or not all(np.isfinite(out)):
        raise config.ConfigError(f"{_WHERE}: demo {name} must be 3 finite numbers, got {value!r}")
    return out


# ----------------------------------------------------------------------------------------- config


@dataclasses.dataclass(frozen=True)
class LawRef:
    """One learned law and the object it drives (``demo.interaction.a`` / ``.b``)."""

    scene: str = "ball"  # scene the law was trained on: runs/<scene>/<method>/law.pt
    method: str = "gca"  # method (table row) whose law is used
    object: str = dataclasses.field(default="", metadata=config.OPTIONAL)  # object whose particles/Gaussians it drives; "" = the scene's own object


@dataclasses.dataclass(frozen=True)
class NewShapeConfig:
    """The new-shape demo (``demo.new_shape``): one scene's law on another object."""

    law_scene: str = "cat"  # scene whose learned law is borrowed
    method: str = "gca"  # method whose law is borrowed
    object: str = "ball"  # object it is applied to (data/particles/<object>.npz)
    v0: tuple[float, float, float] = (0.5, -2.0, 0.0)  # launch velocity [m/s], sim frame
    w0: tuple[float, float, float] = (0.0, 0.0, 2.0)  # launch angular velocity about the COM [rad/s]

    def __post_init__(self):
        object.__setattr__(self, "v0", _vec3(self.v0, "new_shape.v0"))
        object.__setattr__(self, "w0", _vec3(self.w0, "new_shape.w0"))


@dataclasses.dataclass(frozen=True)
class InteractionConfig:
    """The two-object demo (``demo.interaction``): two learned laws in one simulation."""

    a: LawRef = LawRef("ball", "gca")  # first object (particles 0 .. P_a - 1); left / bottom
    b: LawRef = LawRef("cat", "gca")  # second object (particles P_a ..); right / top
    v0_a: tuple[float, float, float] = (2.0, 0.5, 0.0)  # launch velocity of a [m/s]
    v0_b: tuple[float, float, float] = (-2.0, 0.5, 0.0)  # launch velocity of b [m/s]
    layout: str = "side_by_side"  # side_by_side (a at -x, b at +x) | stacked (b above a)
    gap: float = 0.05  # free space between the two objects' boxes along the layout axis [m, sim]

    def __post_init__(self):
        object.__setattr__(self, "v0_a", _vec3(self.v0_a, "interaction.v0_a"))
        object.__setattr__(self, "v0_b", _vec3(self.v0_b, "interaction.v0_b"))
        if self.layout not in LAYOUTS or not self.gap >= 0:
            raise config.ConfigError(f"{_WHERE}: demo.interaction needs layout in {LAYOUTS} and gap >= 0 m, "
                                     f"got layout={self.layout!r}, gap={self.gap}")


@dataclasses.dataclass(frozen=True)
class CaptureDemoConfig:
    """A capture's new-scene demo (``demo.captures.<scene>``, README "Your own object"): the law learned on the
    capture scene drives an object placed elsewhere (raised, turned) and launched anew, filmed by the capture's
    own camera over its plate at the video's frame rate."""

    object: str = "example_capture"  # object the law drives (data/particles/<object>.npz): the captured one, or another
    method: str = "gca"  # method whose learned law is used (runs/<scene>/<method>/law.pt)
    lift: float = 0.1  # raised this much above where the particles stage rests it [m, sim]
    rotation_deg: tuple[float, float, float] = (0.0, 0.0, 30.0)  # turned about its centre: x, then y, then z [deg]
    v0: tuple[float, float, float] = (-0.8, -1.0, 0.0)  # launch velocity [m/s], sim frame
    w0: tuple[float, float, float] = (0.0, 3.0, 0.0)  # launch angular velocity about the centre of mass [rad/s]

    def __post_init__(self):
        for name in ("rotation_deg", "v0", "w0"):
            object.__setattr__(self, name, _vec3(getattr(self, name), f"captures.{name}"))
        if not 0 <= self.lift < 0.5:
            raise config.ConfigError(f"{_WHERE}: demo.captures lift={self.lift} must lie in [0, 0.5) m")


@dataclasses.dataclass(frozen=True)
class DemoConfig:
    """Knobs of the demo stage (params.yaml section ``demo``). Defaults are paper scale."""

    new_shape: NewShapeConfig = NewShapeConfig()
    interaction: InteractionConfig = InteractionConfig()
    n_frames: int = 200  # simulated frames (each steps_per_frame MPM steps); CI ~12 [count]
    steps_per_frame: int = 4  # MPM steps per frame; dt is the smallest dt of the scenes involved [count]
    resolution: int = 256  # square image side [px]; CI ~64
    render_every: int = 1  # the GIF shows every k-th simulated frame (and always the last) [count]
    camera: OrbitCamera = OrbitCamera(azimuth_deg=0.0, elevation_deg=20.0, distance=1.3,
                                      target=(0.5, 0.25, 0.5))  # orbit camera, sim frame
    sweep_deg: float = 60.0  # camera azimuth sweep over the animation (0 = fixed camera) [deg]
    strip_frames: int = 6  # frames in the strip PNG, evenly spaced [count]
    frame_ms: float = 40.0  # GIF frame duration [ms]
    margin: float = 0.1  # interaction: min distance of the pair to the side walls and the ceiling [m, sim]
    floor_gap: float = 0.15  # interaction: the pair's lowest point above the floor at launch [m, sim]
    missing_law: str = "prior"  # no law.pt: "prior" (warn, use the scene's prior) | "error" (raise)
    captures: Mapping[str, CaptureDemoConfig] = dataclasses.field(  # capture scene -> its new-scene demo
        default_factory=lambda: {"example_capture": CaptureDemoConfig()})

    def __post_init__(self):
        problems = []
        if int(self.n_frames) != self.n_frames or self.n_frames < 1:
            problems.append(f"n_frames={self.n_frames} must be an integer >= 1")
        if int(self.steps_per_frame) != self.steps_per_frame or self.steps_per_frame < 1:
            problems.append(f"steps_per_frame={self.steps_per_frame} must be an integer >= 1")
        if self.resolution < 8 or self.strip_frames < 1 or self.render_every < 1 or not self.frame_ms > 0:
            problems.append("need resolution >= 8 px, strip_frames >= 1, render_every >= 1, frame_ms > 0")
        if not 0 <= self.margin < 0.5 or not 0 <= self.floor_gap < 0.5:
            problems.append(f"margin={self.margin} and floor_gap={self.floor_gap} must lie in [0, 0.5) m")
        if self.missing_law not in MISSING_LAW:
            problems.append(f"missing_law={self.missing_law!r} must be one of {MISSING_LAW}")
        if problems:
            raise config.ConfigError(f"{_WHERE}: bad demo config: " + "; ".join(problems))


# ------------------------------------------------------------------------------------ combining


def body_bounds(body: Body) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box of the particles and the Gaussian centres: ``(lo [3], hi [3])`` [m, sim].

    The Gaussians sit on the surface, up to a lattice spacing outside the particles, so the visible
    object fills this box.
    """
    x = torch.cat([body.x0, body.means0]).detach().cpu().double()
    return x.min(0).values.numpy(), x.max(0).values.numpy()


def transform_body(body: Body, scale: float, offset: Sequence[float]) -> Body:
    """Apply the similarity ``x -> scale * x + offset`` to a body (particles and Gaussians).

    Volumes and masses scale by ``scale^3`` (density kept), covariances by ``scale^2``; the
    binding, colours and opacities are unchanged.

    Args:
        body: the body [P particles, G Gaussians].
        scale: uniform scale s > 0 [1].
        offset: translation t [3] [m, sim].
    """
    if not scale > 0:
        raise ValueError(f"{_WHERE}: transform_body: scale must be > 0, got {scale}")
    t = torch.as_tensor(offset, dtype=body.x0.dtype, device=body.x0.device)
    assert t.shape == (3,), f"{_WHERE}: transform_body: offset must have 3 entries, got {tuple(t.shape)}"
    s = float(scale)
    return dataclasses.replace(body, x0=s * body.x0 + t, vol=s ** 3 * body.vol, mass=s ** 3 * body.mass,
                               means0=s * body.means0 + t, covs0=s ** 2 * body.covs0)


def fit_scale(extent_a: np.ndarray, extent_b: np.ndarray, layout: str, gap: float, margin: float,
              floor_gap: float) -> float:
    """Largest common scale s <= 1 at which the pair fits the unit cube.

    Args:
        extent_a, extent_b: object box sizes [3] (:func:`body_bounds`) [m, sim].
        layout: ``side_by_side`` (along x) or ``stacked`` (along y).
        gap: free space between the boxes along the layout axis [m].
        margin: distance kept to the side walls and the ceiling [m].
        floor_gap: height of the lowest particle above the floor [m].
    """
    room = np.array([1 - 2 * margin, 1 - margin - floor_gap, 1 - 2 * margin])
    axis = 0 if layout == "side_by_side" else 1
    along = room[axis] - gap
    if along <= 0 or min(room) <= 0:
        raise ValueError(f"{_WHERE}: no room for the pair: gap {gap} m, margin {margin} m, floor_gap {floor_gap} m")
    limits = [along / (extent_a[axis] + extent_b[axis])]
    limits += [room[k] / max(extent_a[k], extent_b[k]) for k in range(3) if k != axis]
    return float(min(1.0, *limits))


def arrange_pair(a: Body, b: Body, layout: str, gap: float, margin: float, floor_gap: float
                 ) -> tuple[Body, Body, float]:
    """Scale both bodies by one factor and move them apart so they fit the cube without overlapping.

    ``side_by_side``: a at -x, b at +x, the pair centred in x, each centred in z, both resting
    ``floor_gap`` above the floor. ``stacked``: a at the bottom (``floor_gap`` above the floor), b
    ``gap`` above a's top; both centred in x and z.

    Returns:
        ``(a', b', scale)``.
    """
    if layout not in LAYOUTS:
        raise ValueError(f"{_WHERE}: unknown layout {layout!r}; valid: {LAYOUTS}")
    (lo_a, hi_a), (lo_b, hi_b) = body_bounds(a), body_bounds(b)
    ext_a, ext_b = hi_a - lo_a, hi_b - lo_b
    s = fit_scale(ext_a, ext_b, layout, gap, margin, floor_gap)
    start_a = np.array([0.5 - s * ext_a[0] / 2, floor_gap, 0.5 - s * ext_a[2] / 2])
    start_b = np.array([0.5 - s * ext_b[0] / 2, floor_gap, 0.5 - s * ext_b[2] / 2])
    if layout == "side_by_side":
        start_a[0] = 0.5 - (s * (ext_a[0] + ext_b[0]) + gap) / 2
        start_b[0] = start_a[0] + s * ext_a[0] + gap
    else:
        start_b[1] = floor_gap + s * ext_a[1] + gap
    return transform_body(a, s, start_a - s * lo_a), transform_body(b, s, start_b - s * lo_b), s


def concat_bodies(bodies: Sequence[Body]) -> Body:
    """One body from several: particles and Gaussians concatenated in order, binding indices offset.

    Args:
        bodies: bodies with ``P_k`` particles and ``G_k`` Gaussians each (same dtype and device).

    Returns:
        A body with ``sum P_k`` particles and ``sum G_k`` Gaussians; body k's particles are the
        contiguous range starting at ``P_0 + ... + P_{k-1}``.
    """
    if not bodies:
        raise ValueError(f"{_WHERE}: concat_bodies needs at least one body")
    p_off = np.cumsum([0] + [b.n_particles for b in bodies])
    g_off = np.cumsum([0] + [b.n_gaussians for b in bodies])
    binding = Binding(rows=torch.cat([b.binding.rows + int(o) for b, o in zip(bodies, g_off)]),
                      cols=torch.cat([b.binding.cols + int(o) for b, o in zip(bodies, p_off)]),
                      weights=torch.cat([b.binding.weights for b in bodies]),
                      n_gaussians=int(g_off[-1]), n_particles=int(p_off[-1]))
    cat = lambda name: torch.cat([getattr(b, name) for b in bodies])  # noqa: E731
    return Body(x0=cat("x0"), vol=cat("vol"), mass=cat("mass"), binding=binding, means0=cat("means0"),
                covs0=cat("covs0"), colors=cat("colors"), opacities=cat("opacities"))


def density(body: Body) -> float:
    """Mean density of a body, total mass over total volume [kg/m^3]."""
    return float(body.mass.sum() / body.vol.sum())


# ---------------------------------------------------------------------------------------- metrics


def max_strain(F: torch.Tensor) -> float:
    """Largest principal strain ``max |sigma - 1|`` over particles (and frames) of F [..., 3, 3]."""
    assert F.shape[-2:] == (3, 3), f"{_WHERE}: max_strain: F must be [..., 3, 3], got {tuple(F.shape)}"
    flat = F.detach().reshape(-1, 3, 3)
    worst = [(torch.linalg.svdvals(chunk) - 1).abs().max() for chunk in flat.split(1 << 16)]
    return float(torch.stack(worst).max())


def motion_metrics(x: torch.Tensor, F: torch.Tensor, mass: torch.Tensor) -> dict:
    """What a user checks to see a demo behaved.

    Args:
        x: positions [T + 1, P, 3] (m, sim frame), frame 0 the launch state.
        F: elastic deformation gradients [T + 1, P, 3, 3].
        mass: particle masses [P] (kg).

    Returns:
        ``frames`` (T), ``finite`` (every x and F finite), ``com_drop_m`` (launch height of the
        mass-weighted centre of mass minus its lowest height [m]), ``max_strain``
        (max |sigma - 1| over particles and frames [1]), ``com_start`` / ``com_end`` [3] (m).
    """
    T1, P = x.shape[:2]
    assert x.shape == (T1, P, 3) and F.shape == (T1, P, 3, 3) and mass.shape == (P,), \
        f"{_WHERE}: motion_metrics: x [T+1,P,3], F [T+1,P,3,3], mass [P] expected, got " \
        f"{tuple(x.shape)}, {tuple(F.shape)}, {tuple(mass.shape)}"
    x, F = x.detach(), F.detach()
    com = (x * mass[None, :, None]).sum(1) / mass.sum()
    finite = bool(torch.isfinite(x).all() and torch.isfinite(F).all())
    return {"frames": T1 - 1, "finite": finite, "com_drop_m": float(com[0, 1] - com[:, 1].min()),
            "max_strain": max_strain(F) if finite else float("nan"),
            "com_start": com[0].tolist(), "com_end": com[-1].tolist()}


def approach_metrics(x: torch.Tensor, mass: torch.Tensor, n_a: int) -> dict:
    """Distance between the two objects' centres of mass: at launch and its minimum [m].

    Args:
        x: positions [T + 1, P, 3]; particles ``:n_a`` are object a, the rest object b.
        mass: masses [P] (kg).
        n_a: particles of object a.
    """
    assert x.ndim == 3 and 0 < n_a < x.shape[1], f"{_WHERE}: approach_metrics: bad split {n_a} of {tuple(x.shape)}"
    coms = [(xk * mk[None, :, None]).sum(1) / mk.sum()
            for xk, mk in zip(x.detach().split([n_a, x.shape[1] - n_a], 1), mass.split([n_a, x.shape[1] - n_a]))]
    d = (coms[0] - coms[1]).norm(dim=1)
    return {"com_distance_start_m": float(d[0]), "com_distance_min_m": float(d.min())}


# ------------------------------------------------------------------------------- simulate, render


def simulate(solver: MPMSolver, material, body: Body, v: torch.Tensor, n_frames: int,
             steps_per_frame: int) -> tuple[Rollout, float]:
    """Roll ``material`` out from the body's rest state with velocities ``v [P, 3]`` (no gradients).

    Returns:
        The rollout (``n_frames + 1`` frames) and its wall time [s].

    Raises:
        SimulationDiverged: non-finite or runaway state (from :func:`gca.sim.rollout.rollout`).
    """
    assert v.shape == (body.n_particles, 3), \
        f"{_WHERE}: simulate: v must be [{body.n_particles}, 3], got {tuple(v.shape)}"
    t0 = time.perf_counter()
    with torch.no_grad():
        traj = rollout(solver, material, body.x0, v, body.vol, body.mass, n_steps=n_frames * steps_per_frame,
                       steps_per_frame=steps_per_frame, checkpoint=False)
    return traj, time.perf_counter() - t0


def frame_camera(spec: OrbitCamera, resolution: int, frame: int, n_frames: int, sweep_deg: float) -> Camera:
    """The orbit camera of animation frame ``frame`` of ``n_frames``: azimuth advanced by its share of the sweep."""
    azimuth = spec.azimuth_deg + sweep_deg * frame / max(n_frames, 1)
    return make_camera(dataclasses.replace(spec, azimuth_deg=azimuth), resolution)


def shown_frames(n_frames: int, every: int) -> list[int]:
    """Frame indices the animation shows: 0, every, 2 every, ... and always the last one ``n_frames``."""
    return sorted(set(range(0, n_frames + 1, every)) | {n_frames})


def render_frames(body: Body, traj: Rollout, cfg: DemoConfig, background) -> np.ndarray:
    """Render the shown frames of a rollout (:func:`shown_frames`): uint8 RGB ``[K, H, W, 3]``."""
    frames = []
    n = traj.x.shape[0] - 1
    with torch.no_grad():
        for f in shown_frames(n, cfg.render_every):
            camera = frame_camera(cfg.camera, cfg.resolution, f, n, cfg.sweep_deg)
            rgb = render_body(body, traj.x[f], traj.F[f], camera, background)["rgb"]
            frames.append((rgb.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8))
    return np.stack(frames)


def write_animation(out_dir: Path, frames: np.ndarray, strip_frames: int, frame_ms: float) -> dict:
    """Write ``demo.gif`` (every frame) and ``strip.png`` (``strip_frames`` evenly spaced) atomically.

    Args:
        out_dir: folder to write into (created).
        frames: uint8 RGB [T, H, W, 3].
        strip_frames: frames in the strip.
        frame_ms: GIF frame duration [ms].

    Returns:
        ``{"gif": path, "strip_png": path}``.
    """
    assert frames.ndim == 4 and frames.shape[-1] == 3 and frames.dtype == np.uint8, \
        f"{_WHERE}: write_animation: frames must be uint8 [T, H, W, 3], got {frames.dtype} {frames.shape}"
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    idx = np.linspace(0, len(frames) - 1, min(strip_frames, len(frames))).round().astype(int)
    paths = {"gif": out_dir / "demo.gif", "strip_png": out_dir / "strip.png"}
    with atomic_path(paths["gif"]) as tmp:
        iio.imwrite(tmp, frames, extension=".gif", duration=frame_ms, loop=0)
    with atomic_path(paths["strip_png"]) as tmp:
        iio.imwrite(tmp, np.concatenate(list(frames[idx]), axis=1), extension=".png")
    return {k: str(v) for k, v in paths.items()}


def _run(solver: MPMSolver, material, body: Body, v: torch.Tensor, cfg: DemoConfig, out_dir: Path,
         background, parts: Mapping[str, slice]) -> tuple[dict, Rollout | None]:
    """Simulate, summarise each part's motion, render and write; a diverged run reports why."""
    head = {"n_particles": body.n_particles, "n_gaussians": body.n_gaussians, "dt": solver.cfg.dt,
            "steps_per_frame": cfg.steps_per_frame}
    try:
        traj, seconds = simulate(solver, material, body, v, cfg.n_frames, cfg.steps_per_frame)
    except SimulationDiverged as exc:
        warnings.warn(f"{_WHERE}: demo diverged: {exc}", RuntimeWarning, stacklevel=3)
        return {**head, "status": "diverged", "finite": False, "message": str(exc)}, None
    metrics = {**head, "status": "ok", "rollout_seconds": seconds, "max_clamped": int(max(traj.clamped))}
    for name, sl in parts.items():
        part = motion_metrics(traj.x[:, sl], traj.F[:, sl], body.mass[sl])
        if name:
            metrics[name] = part
        else:  # a single object: its metrics at the top level
            metrics.update(part)
    frames = render_frames(body, traj, cfg, background)
    metrics.update(write_animation(out_dir, frames, cfg.strip_frames, cfg.frame_ms), gif_frames=len(frames))
    return metrics, traj


def run_new_shape(solver: MPMSolver, material: Material, body: Body, cfg: DemoConfig, out_dir: Path,
                  background=(1.0, 1.0, 1.0)) -> dict:
    """The new-shape demo: ``material`` drives ``body`` launched with ``cfg.new_shape.v0, w0``.

    Args:
        solver: MPM solver (its dt and grid).
        material: the borrowed law (any material: learned or analytic).
        body: the target object's body (as placed by the particles stage).
        cfg: demo knobs.
        out_dir: receives ``demo.gif`` and ``strip.png``.
        background: RGB in [0, 1].

    Returns:
        Metrics: status, counts, ``frames, finite, com_drop_m, max_strain``, output paths.
    """
    dtype, device = body.x0.dtype, body.x0.device
    v = initial_velocity(body.x0, torch.tensor(cfg.new_shape.v0, dtype=dtype, device=device),
                         torch.tensor(cfg.new_shape.w0, dtype=dtype, device=device))
    metrics, _ = _run(solver, material.to(dtype=dtype, device=device), body, v, cfg, out_dir, background,
                      {"": slice(None)})
    return metrics


def rotation_matrix(degrees: Sequence[float]) -> np.ndarray:
    """The rotation [3, 3] about x, then y, then z by ``degrees`` [deg] (extrinsic: R = Rz Ry Rx)."""
    ax, ay, az = np.radians(np.asarray(degrees, dtype=np.float64))
    rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
    rz = np.array([[np.cos(az), -np.sin(az), 0], [np.sin(az), np.cos(az), 0], [0, 0, 1]])
    return rz @ ry @ rx


def place_body(body: Body, rotation_deg: Sequence[float], lift: float) -> Body:
    """The body turned by ``rotation_deg`` about its particles' centre, then raised ``lift`` [m] and set back on
    its old lowest height (so a turn alone never sinks it into the floor): particles, Gaussian centres and
    covariances (``R Sigma R^T``) move; volumes, masses, the binding and colours stay (SH bands 1-3 are not
    rotated, as with each Gaussian's deformation)."""
    dtype, device = body.x0.dtype, body.x0.device
    R = torch.as_tensor(rotation_matrix(rotation_deg), dtype=dtype, device=device)
    centre = body.x0.mean(0, keepdim=True)
    x0 = (body.x0 - centre) @ R.T + centre
    means0 = (body.means0 - centre) @ R.T + centre
    low_before = torch.cat([body.x0, body.means0])[:, 1].min()
    shift = torch.zeros(3, dtype=dtype, device=device)
    shift[1] = low_before - torch.cat([x0, means0])[:, 1].min() + float(lift)
    return dataclasses.replace(body, x0=x0 + shift, means0=means0 + shift, covs0=R @ body.covs0 @ R.T)


def run_capture_demo(solver: MPMSolver, material: Material, body: Body, cfg: CaptureDemoConfig, camera: Camera,
                     plate: np.ndarray | None, n_frames: int, steps_per_frame: int, demo: DemoConfig, out_dir: Path,
                     background=(1.0, 1.0, 1.0), frame_ms: float | None = None) -> dict:
    """A capture's new-scene demo: ``material`` drives ``body`` placed by :func:`place_body` and launched with
    ``cfg.v0, w0``, filmed from ``camera`` over ``plate`` (the capture's empty scene; None: ``background``).

    Args:
        solver: MPM solver (the capture scene's dt).
        n_frames, steps_per_frame: simulated frames and MPM steps per frame (the video's frame rate).
        demo: the demo section (render_every, strip_frames).
        out_dir: receives ``demo.gif`` and ``strip.png``.
        frame_ms: GIF frame duration [ms] (None: ``demo.frame_ms``).

    Returns:
        Metrics as :func:`run_new_shape`'s, plus the placement (``lift_m``, ``rotation_deg``).
    """
    dtype, device = body.x0.dtype, body.x0.device
    placed = place_body(body, cfg.rotation_deg, cfg.lift)
    v = initial_velocity(placed.x0, torch.tensor(cfg.v0, dtype=dtype, device=device),
                         torch.tensor(cfg.w0, dtype=dtype, device=device))
    head = {"n_particles": body.n_particles, "n_gaussians": body.n_gaussians, "dt": solver.cfg.dt,
            "steps_per_frame": steps_per_frame, "lift_m": cfg.lift, "rotation_deg": list(cfg.rotation_deg)}
    try:
        traj, seconds = simulate(solver, material.to(dtype=dtype, device=device), placed, v, n_frames, steps_per_frame)
    except SimulationDiverged as exc:
        warnings.warn(f"{_WHERE}: capture demo diverged: {exc}", RuntimeWarning, stacklevel=2)
        return {**head, "status": "diverged", "finite": False, "message": str(exc)}
    metrics = {**head, "status": "ok", "rollout_seconds": seconds, "max_clamped": int(max(traj.clamped)),
               **motion_metrics(traj.x, traj.F, placed.mass)}
    bg = torch.zeros(3, dtype=dtype, device=device)
    back = plate if plate is not None else np.broadcast_to(np.asarray(background, np.float32),
                                                           (camera.height, camera.width, 3))
    frames = []
    with torch.no_grad():
        for f in shown_frames(n_frames, demo.render_every):
            out = render_body(placed, traj.x[f], traj.F[f], camera, bg)
            a = out["alpha"].cpu().numpy()[..., None]
            frames.append((np.clip(out["rgb"].cpu().numpy() + (1 - a) * back, 0, 1) * 255 + 0.5).astype(np.uint8))
    metrics.update(write_animation(out_dir, np.stack(frames), demo.strip_frames,
                                   demo.frame_ms if frame_ms is None else frame_ms), gif_frames=len(frames))
    return metrics


def run_interaction(solver: MPMSolver, materials: Sequence[Material], bodies: Sequence[Body], cfg: DemoConfig,
                    out_dir: Path, background=(1.0, 1.0, 1.0)) -> dict:
    """The two-object demo: arrange ``bodies`` (a, b), couple their laws in one simulation, render.

    Args:
        solver: MPM solver.
        materials: (law of a, law of b).
        bodies: (a, b) as loaded; they are rescaled and moved by :func:`arrange_pair`.
        cfg: demo knobs (``cfg.interaction`` gives the layout, gap and launch velocities).
        out_dir: receives ``demo.gif`` and ``strip.png``.
        background: RGB in [0, 1].

    Returns:
        Metrics with per-object entries ``a`` and ``b`` (as :func:`motion_metrics`), the layout
        scale, and the centres' distance at launch and at closest approach.
    """
    if len(materials) != 2 or len(bodies) != 2:
        raise ValueError(f"{_WHERE}: run_interaction needs two materials and two bodies, "
                         f"got {len(materials)} and {len(bodies)}")
    ic = cfg.interaction
    a, b, scale = arrange_pair(bodies[0], bodies[1], ic.layout, ic.gap, cfg.margin, cfg.floor_gap)
    body = concat_bodies([a, b])
    dtype, device = body.x0.dtype, body.x0.device
    material = CompositeMaterial(list(materials), [a.n_particles, b.n_particles]).to(dtype=dtype, device=device)
    v = torch.cat([initial_velocity(a.x0, torch.tensor(ic.v0_a, dtype=dtype, device=device)),
                   initial_velocity(b.x0, torch.tensor(ic.v0_b, dtype=dtype, device=device))])
    parts = {"a": slice(0, a.n_particles), "b": slice(a.n_particles, None)}
    metrics, traj = _run(solver, material, body, v, cfg, out_dir, background, parts)
    metrics.update(layout=ic.layout, scale=scale, n_particles_a=a.n_particles, n_particles_b=b.n_particles)
    if traj is not None:
        metrics.update(approach_metrics(traj.x, body.mass, a.n_particles))
    return metrics
