"""Cantilever beam physics in MuJoCo: config, model, modal analysis, simulation.

The beam stands along +z (clamp at z = 0, tip at z = L) and bends along +x
(the thickness direction), see ``docs/formats.md``. It is a Hencky bar chain:
``n_segments`` rigid links of length ``h = L / n`` joined by hinges about y
with rotational springs, the link masses lumped at the nodes (``m h`` at
interior nodes, ``m h / 2`` at the tip). Interior springs have stiffness
``EI / h`` and the clamp spring ``2 EI / h`` (the clamp node carries half
weight in the trapezoidal curvature energy). The linearised chain is then the
central finite-difference scheme of the Euler-Bernoulli beam, so the natural
frequencies converge at second order in ``h``.

Modal damping ``C = M Phi diag(2 zeta omega) Phi^T M`` is realised exactly as
one damped fixed tendon per mode (tendon coefficients ``M phi_k``), so the
damping runs inside MuJoCo's step with no Python per time step.

References
----------
.. [1] H. Hencky, "Ueber die angenaeherte Loesung von Stabilitaetsproblemen im
   Raum mittels der elastischen Gelenkkette", Der Eisenbau 11 (1920).
.. [2] C. M. Wang, H. Zhang, N. Challamel, W. H. Duan, "Eringen's small length
   scale coefficient for vibration of axially loaded nonlocal Euler beams
   with elastic end restraints", (Hencky chain = central FD of Euler beam).
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import time
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import scipy.linalg
import scipy.optimize
import scipy.signal

from sim.config import STAGE_SECTIONS

GRAVITY_M_S2 = 9.81
#: Euler-Bernoulli cantilever eigenvalues beta_n L (no tip mass).
_BETA_L = (1.8751040687119611, 4.6940911329741745, 7.8547574382376126,
           10.995540734875467, 14.137168391046471, 17.278759532088237)


# ----------------------------------------------------------------------------
# Config
# ----------------------------------------------------------------------------

def _check_keys(section: str, data: Mapping[str, Any], allowed: Sequence[str]) -> None:
    unknown = sorted(set(data) - set(allowed))
    if unknown:
        raise ValueError(f"unknown key(s) in {section}: {unknown}; allowed: {sorted(allowed)}")


def _positive(name: str, value: float) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number > 0, got {value!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be > 0, got {value!r}")
    return value


def _non_negative(name: str, value: float) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number >= 0, got {value!r}") from None
    if not math.isfinite(value) or value < 0:
        raise ValueError(f"{name} must be >= 0, got {value!r}")
    return value


@dataclass(frozen=True)
class BeamParams:
    """Geometry and material of the cantilever (defaults: the paper's steel strip)."""

    length_mm: float = 1000.0
    width_mm: float = 100.0
    thickness_mm: float = 5.0
    youngs_modulus_gpa: float = 200.0
    density_kg_m3: float = 7850.0
    n_segments: int = 50
    gravity: bool = True
    tip_mass_kg: float = 0.0

    MIN_SEGMENTS = 4

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> BeamParams:
        data = dict(data or {})
        _check_keys("beam", data, [f.name for f in dataclasses.fields(cls)])
        kw: dict[str, Any] = {}
        for key in ("length_mm", "width_mm", "thickness_mm", "youngs_modulus_gpa", "density_kg_m3"):
            if key in data:
                kw[key] = _positive(f"beam.{key}", data[key])
        if "tip_mass_kg" in data:
            kw["tip_mass_kg"] = _non_negative("beam.tip_mass_kg", data["tip_mass_kg"])
        if "n_segments" in data:
            n = data["n_segments"]
            if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < cls.MIN_SEGMENTS:
                raise ValueError(f"beam.n_segments must be an integer >= {cls.MIN_SEGMENTS}, got {n!r}")
            kw["n_segments"] = int(n)
        if "gravity" in data:
            if not isinstance(data["gravity"], bool):
                raise ValueError(f"beam.gravity must be true or false, got {data['gravity']!r}")
            kw["gravity"] = data["gravity"]
        return cls(**kw)

    # Derived SI quantities
    @property
    def length_m(self) -> float:
        return self.length_mm * 1e-3

    @property
    def bending_stiffness_n_m2(self) -> float:
        """EI about y (bending along x, the thickness direction)."""
        width, thick = self.width_mm * 1e-3, self.thickness_mm * 1e-3
        return self.youngs_modulus_gpa * 1e9 * width * thick**3 / 12.0

    @property
    def mass_per_length_kg_m(self) -> float:
        return self.density_kg_m3 * self.width_mm * 1e-3 * self.thickness_mm * 1e-3


@dataclass(frozen=True)
class DampingParams:
    """Modal damping ratios, mode 1 first; later modes reuse the last ratio."""

    ratios: tuple[float, ...] = (0.005, 0.005, 0.005)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> DampingParams:
        data = dict(data or {})
        _check_keys("damping", data, ["ratios"])
        if "ratios" not in data:
            return cls()
        ratios = data["ratios"]
        if isinstance(ratios, (int, float)):
            ratios = [ratios]
        if not isinstance(ratios, (list, tuple)) or not ratios:
            raise ValueError(f"damping.ratios must be a non-empty list of numbers, got {ratios!r}")
        out = []
        for i, zeta in enumerate(ratios):
            try:
                zeta_f = float(zeta)
            except (TypeError, ValueError):
                raise ValueError(f"damping.ratios[{i}] must be a number, got {zeta!r}") from None
            if not (0.0 <= zeta_f < 1.0):
                raise ValueError(f"damping.ratios[{i}] must be in [0, 1), got {zeta!r}")
            out.append(zeta_f)
        return cls(ratios=tuple(out))

    def ratio(self, mode_index: int) -> float:
        return self.ratios[min(mode_index, len(self.ratios) - 1)]


@dataclass(frozen=True)
class SensorParams:
    """Laser point(s) and the sampling rates of the outputs."""

    height_mm: float = 750.0
    extra_heights_mm: tuple[float, ...] = ()
    rate_hz: float = 1000.0
    shape_rate_hz: float = 1000.0

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> SensorParams:
        data = dict(data or {})
        _check_keys("sensor", data, [f.name for f in dataclasses.fields(cls)])
        kw: dict[str, Any] = {}
        for key in ("height_mm", "rate_hz", "shape_rate_hz"):
            if key in data:
                kw[key] = _positive(f"sensor.{key}", data[key])
        if "extra_heights_mm" in data:
            extra = data["extra_heights_mm"]
            if not isinstance(extra, (list, tuple)):
                raise ValueError(f"sensor.extra_heights_mm must be a list, got {extra!r}")
            kw["extra_heights_mm"] = tuple(_positive(f"sensor.extra_heights_mm[{i}]", h)
                                           for i, h in enumerate(extra))
        return cls(**kw)


_EXCITATION_KEYS = {
    "pluck": {"start_s": 0.0, "peak_mm": 1.8, "height_mm": None, "load_height_mm": None},
    "impulse": {"start_s": 0.1, "height_mm": 1000.0, "impulse_ns": 0.05},
    "harmonic": {"start_s": 0.0, "stop_s": None, "height_mm": 1000.0, "freq_hz": 4.0,
                 "amplitude_n": 0.05},
    "ambient": {"start_s": 0.0, "stop_s": None, "rms_m_s2": 0.05, "band_hz": [1.0, 100.0]},
}


@dataclass(frozen=True)
class Excitation:
    """One excitation component.

    ``pluck``: held at the static shape of a load at ``load_height_mm`` (default
    the tip) scaled so the point at ``height_mm`` (default the sensor) is
    deflected ``peak_mm``, released at ``start_s``.
    ``impulse``: hammer blow of ``impulse_ns`` (N s) along +x at ``height_mm``.
    ``harmonic``: force ``amplitude_n sin(2 pi freq_hz (t - start_s))`` along +x.
    ``ambient``: band-limited Gaussian base acceleration (``rms_m_s2``, ``band_hz``)
    seeded from the config ``seed``; displacements are relative to the base.
    While a pluck holds the beam (``t < start_s`` of the pluck) other forcing is
    ignored; after that all components are summed.
    """

    type: str
    params: tuple[tuple[str, Any], ...]

    def get(self, key: str) -> Any:
        return dict(self.params)[key]

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], index: int) -> Excitation:
        where = f"excitation[{index}]"
        if not isinstance(data, Mapping) or "type" not in data:
            raise ValueError(f"{where} must be a mapping with a 'type', got {data!r}")
        kind = data["type"]
        if kind not in _EXCITATION_KEYS:
            raise ValueError(f"{where}.type must be one of {sorted(_EXCITATION_KEYS)}, got {kind!r}")
        defaults = _EXCITATION_KEYS[kind]
        rest = {k: v for k, v in data.items() if k != "type"}
        _check_keys(where, rest, list(defaults))
        params = dict(defaults)
        params.update(rest)
        for key, value in list(params.items()):
            if value is None:
                continue
            name = f"{where}.{key}"
            if key in ("start_s",):
                params[key] = _non_negative(name, value)
            elif key == "band_hz":
                if not isinstance(value, (list, tuple)) or len(value) != 2:
                    raise ValueError(f"{name} must be [low, high], got {value!r}")
                low, high = (_positive(name, v) for v in value)
                if low >= high:
                    raise ValueError(f"{name} must have low < high, got {value!r}")
                params[key] = (low, high)
            elif key in ("rms_m_s2",):
                params[key] = _non_negative(name, value)
            elif key in ("peak_mm", "impulse_ns", "amplitude_n"):
                try:
                    params[key] = float(value)
                except (TypeError, ValueError):
                    raise ValueError(f"{name} must be a number, got {value!r}") from None
                if not math.isfinite(params[key]):
                    raise ValueError(f"{name} must be finite, got {value!r}")
            else:
                params[key] = _positive(name, value)
        if params.get("stop_s") is not None and params["stop_s"] <= params["start_s"]:
            raise ValueError(f"{where}.stop_s must be > start_s, got {params['stop_s']!r}")
        return cls(type=kind, params=tuple(sorted(params.items())))


@dataclass(frozen=True)
class SimulationParams:
    """Time integration: ``engine`` mujoco (nonlinear MuJoCo stepping) or modal (exact linear)."""

    engine: str = "modal"
    stability_margin: float = 0.9
    exact_damped_modes: int = 10

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> SimulationParams:
        data = dict(data or {})
        _check_keys("simulation", data, [f.name for f in dataclasses.fields(cls)])
        kw: dict[str, Any] = {}
        if "engine" in data:
            if data["engine"] not in ("mujoco", "modal"):
                raise ValueError(f"simulation.engine must be 'mujoco' or 'modal', got {data['engine']!r}")
            kw["engine"] = data["engine"]
        if "stability_margin" in data:
            margin = _positive("simulation.stability_margin", data["stability_margin"])
            if margin >= 1:
                raise ValueError(f"simulation.stability_margin must be in (0, 1), got {margin!r}")
            kw["stability_margin"] = margin
        if "exact_damped_modes" in data:
            value = data["exact_damped_modes"]
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ValueError(f"simulation.exact_damped_modes must be an integer >= 1, got {value!r}")
            kw["exact_damped_modes"] = int(value)
        return cls(**kw)


def _default_excitation() -> tuple[Excitation, ...]:
    return (Excitation.from_dict({"type": "pluck"}, 0),)


@dataclass(frozen=True)
class SimConfig:
    """The ``sim`` view of a scenario config (other stages' sections are ignored)."""

    seed: int = 0
    duration_s: float = 10.0
    beam: BeamParams = field(default_factory=BeamParams)
    damping: DampingParams = field(default_factory=DampingParams)
    excitation: tuple[Excitation, ...] = field(default_factory=_default_excitation)
    sensor: SensorParams = field(default_factory=SensorParams)
    simulation: SimulationParams = field(default_factory=SimulationParams)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any] | None) -> SimConfig:
        """Build from a scenario dict; missing keys take defaults, bad values raise ValueError."""
        data = dict(data or {})
        seed = data.get("seed", 0)
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
        duration = _positive("duration_s", data.get("duration_s", cls.duration_s))
        beam = BeamParams.from_dict(data.get("beam"))
        damping = DampingParams.from_dict(data.get("damping"))
        sensor = SensorParams.from_dict(data.get("sensor"))
        simulation = SimulationParams.from_dict(data.get("simulation"))
        exc_data = data.get("excitation")
        if exc_data is None:
            excitation = _default_excitation()
        else:
            if isinstance(exc_data, Mapping):
                exc_data = [exc_data]
            if not isinstance(exc_data, (list, tuple)):
                raise ValueError(f"excitation must be a list of components, got {exc_data!r}")
            excitation = tuple(Excitation.from_dict(c, i) for i, c in enumerate(exc_data))
        if sum(e.type == "pluck" for e in excitation) > 1:
            raise ValueError("excitation may hold at most one pluck component")
        for name, height in [("sensor.height_mm", sensor.height_mm)] + [
                (f"sensor.extra_heights_mm[{i}]", h) for i, h in enumerate(sensor.extra_heights_mm)]:
            if height > beam.length_mm:
                raise ValueError(f"{name} must be <= beam.length_mm ({beam.length_mm}), got {height!r}")
        for i, exc in enumerate(excitation):
            for key in ("height_mm", "load_height_mm"):
                value = dict(exc.params).get(key)
                if value is not None and value > beam.length_mm:
                    raise ValueError(f"excitation[{i}].{key} must be <= beam.length_mm "
                                     f"({beam.length_mm}), got {value!r}")
        rates = sorted((sensor.rate_hz, sensor.shape_rate_hz))
        ratio = rates[1] / rates[0]
        if abs(ratio - round(ratio)) > 1e-9:
            raise ValueError(f"sensor.shape_rate_hz ({sensor.shape_rate_hz}) and sensor.rate_hz "
                             f"({sensor.rate_hz}) must be integer multiples of each other")
        return cls(seed=int(seed), duration_s=duration, beam=beam, damping=damping,
                   excitation=excitation, sensor=sensor, simulation=simulation)

    def with_beam(self, **changes: Any) -> SimConfig:
        return dataclasses.replace(self, beam=dataclasses.replace(self.beam, **changes))


def _as_config(cfg: SimConfig | Mapping[str, Any] | None) -> SimConfig:
    return cfg if isinstance(cfg, SimConfig) else SimConfig.from_dict(cfg)


# ----------------------------------------------------------------------------
# Reference: Euler-Bernoulli
# ----------------------------------------------------------------------------

def euler_bernoulli_hz(cfg: SimConfig | BeamParams | Mapping[str, Any] | None = None,
                       n: int = 3) -> np.ndarray:
    """First ``n`` natural frequencies (Hz) of the continuous Euler-Bernoulli cantilever.

    Includes the tip mass (frequency equation with an end mass), not gravity.
    """
    beam = cfg if isinstance(cfg, BeamParams) else _as_config(cfg).beam
    length = beam.length_m
    mass_ratio = beam.tip_mass_kg / (beam.mass_per_length_kg_m * length)

    def char(x: float) -> float:
        # Divided by cosh(x) to stay finite for large x.
        c, s = math.cos(x), math.sin(x)
        return (1.0 / math.cosh(x) + c + mass_ratio * x * (c * math.tanh(x) - s))

    roots: list[float] = []
    grid = np.linspace(1e-6, (n + 2) * math.pi, 400 * (n + 2))
    values = [char(x) for x in grid]
    for a, b, fa, fb in zip(grid[:-1], grid[1:], values[:-1], values[1:], strict=True):
        if fa == 0 or fa * fb < 0:
            roots.append(scipy.optimize.brentq(char, a, b, xtol=1e-14))
            if len(roots) == n:
                break
    beta = np.array(roots) / length
    omega = beta**2 * math.sqrt(beam.bending_stiffness_n_m2 / beam.mass_per_length_kg_m)
    return omega / (2 * math.pi)


def euler_bernoulli_shapes(z_m: np.ndarray, length_m: float, n: int) -> np.ndarray:
    """Analytic cantilever mode shapes (no tip mass) at heights ``z_m``, shape (n, len(z))."""
    shapes = []
    for bl in _BETA_L[:n]:
        x = bl * np.asarray(z_m) / length_m
        sigma = (math.sinh(bl) - math.sin(bl)) / (math.cosh(bl) + math.cos(bl))
        shapes.append(np.cosh(x) - np.cos(x) - sigma * (np.sinh(x) - np.sin(x)))
    return np.array(shapes)


# ----------------------------------------------------------------------------
# Model
# ----------------------------------------------------------------------------

def node_heights_m(beam: BeamParams) -> np.ndarray:
    """Undeformed node heights z (m), clamp node first, tip last (n_segments + 1)."""
    return np.linspace(0.0, beam.length_m, beam.n_segments + 1)


def _segment_masses(beam: BeamParams) -> np.ndarray:
    h = beam.length_m / beam.n_segments
    masses = np.full(beam.n_segments, beam.mass_per_length_kg_m * h)
    masses[-1] = 0.5 * masses[-1] + beam.tip_mass_kg
    return masses


def _spring_stiffness(beam: BeamParams) -> np.ndarray:
    h = beam.length_m / beam.n_segments
    stiff = np.full(beam.n_segments, beam.bending_stiffness_n_m2 / h)
    stiff[0] *= 2.0
    return stiff


def _point_location(beam: BeamParams, height_mm: float) -> tuple[int, float]:
    """Segment index and height above that segment's hinge (m) of a material point."""
    h = beam.length_m / beam.n_segments
    z = height_mm * 1e-3
    index = min(int(z // h), beam.n_segments - 1)
    return index, z - index * h


def build_mjcf(cfg: SimConfig | Mapping[str, Any] | None = None, *,
               damping_coefs: np.ndarray | None = None,
               damping_values: np.ndarray | None = None,
               base_accel_coefs: np.ndarray | None = None,
               force_heights_mm: Sequence[float] = (),
               timestep_s: float = 1e-4,
               integrator: str = "implicitfast") -> str:
    """MJCF text of the bar chain.

    ``damping_coefs`` (modes x joints) and ``damping_values`` add one damped fixed
    tendon per mode; ``base_accel_coefs`` adds a tendon actuator whose control is
    the base acceleration (m/s^2); each of ``force_heights_mm`` gets a site and a
    force actuator along the local x axis (N).
    """
    cfg = _as_config(cfg)
    beam = cfg.beam
    n = beam.n_segments
    h = beam.length_m / n
    masses = _segment_masses(beam)
    stiffness = _spring_stiffness(beam)
    gravity = GRAVITY_M_S2 if beam.gravity else 0.0
    sites: dict[int, list[tuple[int, float]]] = {}
    for k, height in enumerate(force_heights_mm):
        index, local = _point_location(beam, height)
        sites.setdefault(index, []).append((k, local))

    lines = ['<mujoco model="cantilever">',
             '  <compiler angle="radian" autolimits="true"/>',
             f'  <option timestep="{float(timestep_s)!r}" integrator="{integrator}" '
             f'gravity="0 0 {float(-gravity)!r}">',
             # No geoms, contacts or constraints: skip those pipeline stages.
             '    <flag contact="disable" constraint="disable"/>',
             '  </option>',
             '  <worldbody>']
    indent = "    "
    for i in range(n):
        pos = "0 0 0" if i == 0 else f"0 0 {float(h)!r}"
        # Euler-Bernoulli has no rotary inertia: keep the link inertia negligible.
        inertia = masses[i] * 1e-9
        lines.append(f'{indent}<body name="seg{i}" pos="{pos}">')
        lines.append(f'{indent}  <joint name="j{i}" type="hinge" axis="0 1 0" pos="0 0 0" '
                     f'stiffness="{float(stiffness[i])!r}" springref="0" armature="0" damping="0"/>')
        lines.append(f'{indent}  <inertial pos="0 0 {float(h)!r}" mass="{float(masses[i])!r}" '
                     f'diaginertia="{float(inertia)!r} {float(inertia)!r} {float(inertia)!r}"/>')
        for k, local in sites.get(i, []):
            lines.append(f'{indent}  <site name="force{k}" pos="0 0 {float(local)!r}"/>')
        indent += "  "
    for _ in range(n):
        indent = indent[:-2]
        lines.append(f"{indent}</body>")
    lines.append("  </worldbody>")
    tendons = []
    if damping_coefs is not None:
        for k, (coefs, value) in enumerate(zip(damping_coefs, damping_values, strict=True)):
            tendons.append(f'    <fixed name="mode{k}" damping="{float(value)!r}">')
            tendons += [f'      <joint joint="j{j}" coef="{float(c)!r}"/>' for j, c in enumerate(coefs)]
            tendons.append("    </fixed>")
    if base_accel_coefs is not None:
        tendons.append('    <fixed name="base_accel">')
        tendons += [f'      <joint joint="j{j}" coef="{float(c)!r}"/>'
                    for j, c in enumerate(base_accel_coefs)]
        tendons.append("    </fixed>")
    if tendons:
        lines += ["  <tendon>", *tendons, "  </tendon>"]
    actuators = [f'    <general name="force{k}" site="force{k}" gear="1 0 0 0 0 0"/>'
                 for k in range(len(force_heights_mm))]
    if base_accel_coefs is not None:
        actuators.append('    <general name="base_accel" tendon="base_accel" gear="1"/>')
    if actuators:
        lines += ["  <actuator>", *actuators, "  </actuator>"]
    lines.append("</mujoco>")
    return "\n".join(lines) + "\n"


def build_model(cfg: SimConfig | Mapping[str, Any] | None = None, **kwargs: Any) -> mujoco.MjModel:
    """Compile the bar chain (see :func:`build_mjcf` for the keyword options)."""
    return mujoco.MjModel.from_xml_string(build_mjcf(cfg, **kwargs))


def _mass_stiffness(model: mujoco.MjModel) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mass (mj_fullM), spring stiffness and gravity geometric stiffness at q = 0."""
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    nv = model.nv
    mass = np.zeros((nv, nv))
    mujoco.mj_fullM(model, data, mass)
    spring = np.diag(model.jnt_stiffness.copy())
    # Gravity enters qfrc_bias as dV/dq; its Jacobian is the geometric stiffness.
    # qfrc_bias is odd in q about the straight beam, so central differences have
    # an O(eps^2) = 1e-12 relative error.
    eps = 1e-6
    geometric = np.zeros((nv, nv))
    for j in range(nv):
        cols = []
        for sign in (1.0, -1.0):
            data.qpos[:] = 0.0
            data.qvel[:] = 0.0
            data.qpos[j] = sign * eps
            mujoco.mj_forward(model, data)
            cols.append(data.qfrc_bias.copy())
        geometric[:, j] = (cols[0] - cols[1]) / (2 * eps)
    geometric = 0.5 * (geometric + geometric.T)
    return mass, spring, geometric


def _eigen(mass: np.ndarray, stiffness: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angular frequencies (rad/s) and mass-normalised modes (columns)."""
    eigvals, modes = scipy.linalg.eigh(stiffness, mass)
    if eigvals[0] <= 0:
        raise ValueError("the beam buckles under its own weight (negative stiffness): "
                         "shorten it, stiffen it or set beam.gravity false")
    return np.sqrt(eigvals), modes


def _node_displacements(beam: BeamParams, qpos: np.ndarray) -> tuple[np.ndarray, ...]:
    """Node x, z (m) and section rotation (rad) from hinge angles, exact chain kinematics.

    ``qpos`` has shape (..., n_segments); outputs have n_segments + 1 nodes.
    """
    h = beam.length_m / beam.n_segments
    phi = np.cumsum(qpos, axis=-1)  # absolute link angles
    zeros = np.zeros(qpos.shape[:-1] + (1,))
    x = np.concatenate([zeros, h * np.cumsum(np.sin(phi), axis=-1)], axis=-1)
    z = np.concatenate([zeros, h * np.cumsum(np.cos(phi), axis=-1)], axis=-1)
    # Node rotation: mean of the two links meeting there (clamp 0, tip = last link).
    theta = np.concatenate([zeros, 0.5 * (phi[..., :-1] + phi[..., 1:]), phi[..., -1:]], axis=-1)
    return x, z, theta


def _point_x(beam: BeamParams, node_x: np.ndarray, height_mm: float) -> np.ndarray:
    """Lateral displacement of the material point at ``height_mm``: along its rigid link."""
    index, local = _point_location(beam, height_mm)
    frac = local / (beam.length_m / beam.n_segments)
    return (1.0 - frac) * node_x[..., index] + frac * node_x[..., index + 1]


def _dof_modal(cfg: SimConfig) -> dict[str, Any]:
    model = build_model(cfg)
    mass, spring, geometric = _mass_stiffness(model)
    omega, modes = _eigen(mass, spring + geometric)
    return {"model": model, "mass": mass, "spring": spring, "geometric": geometric,
            "omega": omega, "modes": modes}


def modal_analysis(cfg: SimConfig | Mapping[str, Any] | None = None, n_modes: int = 3
                   ) -> dict[str, Any]:
    """Natural frequencies, mode shapes and damping of the MuJoCo model.

    Mass from ``mj_fullM``, stiffness from the joint springs plus the gravity
    geometric stiffness. Returns JSON-ready lists; ``model_hz_no_gravity`` is
    always given so the gravity shift can be read off.
    """
    cfg = _as_config(cfg)
    beam = cfg.beam
    if not 1 <= n_modes <= beam.n_segments:
        raise ValueError(f"n_modes must be in [1, {beam.n_segments}], got {n_modes!r}")
    modal = _dof_modal(cfg)
    freq = modal["omega"][:n_modes] / (2 * math.pi)
    no_grav = modal["omega"] if not beam.gravity else _eigen(
        modal["mass"], modal["spring"])[0]
    z_m = node_heights_m(beam)
    shapes = []
    for k in range(n_modes):
        # Linearised node displacement: x_i = h sum_{j<i} phi_j, phi = cumsum(q).
        x, _, _ = _node_displacements(beam, modal["modes"][:, k] * 1e-6)
        x = x / np.abs(x).max()
        if x[-1] < 0:
            x = -x
        shapes.append(x)
    eb = euler_bernoulli_hz(beam, n_modes)
    analytic = euler_bernoulli_shapes(z_m, beam.length_m, min(n_modes, len(_BETA_L)))
    mac = [float(np.dot(s, a) ** 2 / (np.dot(s, s) * np.dot(a, a)))
           for s, a in zip(shapes, analytic, strict=False)]
    return {
        "model_hz": freq.tolist(),
        "model_hz_no_gravity": (no_grav[:n_modes] / (2 * math.pi)).tolist(),
        "euler_bernoulli_hz": eb.tolist(),
        # Discretisation error: gravity-free model vs the gravity-free continuum.
        "relative_error_no_gravity_vs_euler_bernoulli":
            (no_grav[:n_modes] / (2 * math.pi) / eb - 1).tolist(),
        "gravity": beam.gravity,
        "damping_ratios": [cfg.damping.ratio(k) for k in range(n_modes)],
        "mode_shapes": {"z_mm": (z_m * 1e3).tolist(),
                        "x_normalized": [s.tolist() for s in shapes]},
        "mac_vs_euler_bernoulli": mac if beam.tip_mass_kg == 0 else None,
        "n_segments": beam.n_segments,
        "beam": dataclasses.asdict(beam),
        "bending_stiffness_n_m2": beam.bending_stiffness_n_m2,
        "mass_per_length_kg_m": beam.mass_per_length_kg_m,
        "highest_model_hz": float(modal["omega"][-1] / (2 * math.pi)),
    }


def tune_to_hz(cfg: SimConfig | Mapping[str, Any] | None, target_hz: float, *,
               parameter: str = "youngs_modulus_gpa") -> tuple[SimConfig, dict[str, Any]]:
    """Fit ``beam.youngs_modulus_gpa`` (or ``beam.tip_mass_kg``) so mode 1 is ``target_hz``.

    Mode 1 of the model (gravity included when on) is matched; the tip mass can
    only lower the frequency.
    """
    cfg = _as_config(cfg)
    target_hz = _positive("tune_to_hz", target_hz)
    if parameter not in ("youngs_modulus_gpa", "tip_mass_kg"):
        raise ValueError(f"parameter must be youngs_modulus_gpa or tip_mass_kg, got {parameter!r}")

    def f1(value: float) -> float:
        return _dof_modal(cfg.with_beam(**{parameter: value}))["omega"][0] / (2 * math.pi) - target_hz

    start = getattr(cfg.beam, parameter)
    if parameter == "youngs_modulus_gpa":
        # Without gravity f1 ~ sqrt(E): start from that and bracket.
        guess = start * (target_hz / (f1(start) + target_hz)) ** 2
        low, high = guess * 0.8, guess * 1.25
        while f1(low) > 0:
            low *= 0.7
        while f1(high) < 0:
            high *= 1.5
    else:
        low, high = 0.0, max(1.0, 10 * cfg.beam.mass_per_length_kg_m * cfg.beam.length_m)
        if f1(low) < 0:
            raise ValueError(f"cannot reach {target_hz} Hz with a tip mass: mode 1 is already "
                             f"{f1(low) + target_hz:.4f} Hz without one")
        while f1(high) > 0:
            high *= 4
    value = scipy.optimize.brentq(f1, low, high, xtol=1e-12 * max(1.0, high), rtol=1e-12)
    tuned = cfg.with_beam(**{parameter: value})
    before = _dof_modal(cfg)["omega"][0] / (2 * math.pi)
    return tuned, {"parameter": f"beam.{parameter}", "before": start, "after": value,
                   "mode1_hz_before": before, "target_hz": target_hz}


# ----------------------------------------------------------------------------
# Simulation
# ----------------------------------------------------------------------------

@dataclass
class SimResult:
    """Arrays of one simulation (SI inside, mm in the files)."""

    time_s: np.ndarray
    qpos: np.ndarray
    record_rate_hz: float
    timestep_s: float
    substeps: int
    model_hz: list[float]
    wall_s: float
    excitation_info: list[dict[str, Any]]
    engine: str = "mujoco"


def _ambient_signal(cfg: SimConfig, exc: Excitation, rate_hz: float, n_samples: int,
                    index: int) -> np.ndarray:
    """Band-limited Gaussian base acceleration, seeded from the config seed."""
    rng = np.random.default_rng([cfg.seed, index])
    low, high = exc.get("band_hz")
    high = min(high, 0.45 * rate_hz)
    pad = int(rate_hz * 2)  # filter transient burned before t = 0
    white = rng.standard_normal(n_samples + pad)
    sos = scipy.signal.butter(4, [low, high], btype="bandpass", fs=rate_hz, output="sos")
    signal = scipy.signal.sosfilt(sos, white)[pad:]
    rms = float(np.sqrt(np.mean(signal**2))) or 1.0
    return signal * (exc.get("rms_m_s2") / rms)


def _window(exc: Excitation, t: np.ndarray) -> np.ndarray:
    stop = exc.get("stop_s")
    on = t >= exc.get("start_s")
    if stop is not None:
        on &= t < stop
    return on


def _lever(beam: BeamParams, height_mm: float) -> np.ndarray:
    """Generalized force of a unit +x force at ``height_mm`` (linearised at q = 0)."""
    index, local = _point_location(beam, height_mm)
    h = beam.length_m / beam.n_segments
    lever = np.zeros(beam.n_segments)
    lever[: index + 1] = index * h + local - np.arange(index + 1) * h
    return lever


def _base_accel_vector(model: mujoco.MjModel) -> np.ndarray:
    """Generalized force per unit base acceleration along x: -sum_j m_j J_j^T x."""
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    vector = np.zeros(model.nv)
    jacp = np.zeros((3, model.nv))
    for body in range(1, model.nbody):
        mujoco.mj_jacBodyCom(model, data, jacp, None, body)
        vector -= model.body_mass[body] * jacp[0]
    return vector


def _modal_step_matrices(omega: np.ndarray, zeta: np.ndarray, dt: float
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Exact per-mode transition (n, 2, 2) and ZOH input (n, 2) matrices over ``dt``."""
    transition = np.zeros((omega.size, 2, 2))
    zoh = np.zeros((omega.size, 2))
    for k, (w, z) in enumerate(zip(omega, zeta, strict=True)):
        a = np.array([[0.0, 1.0, 0.0], [-w * w, -2 * z * w, 1.0], [0.0, 0.0, 0.0]])
        e = scipy.linalg.expm(a * dt)
        transition[k] = e[:2, :2]
        zoh[k] = e[:2, 2]
    return transition, zoh


@dataclass
class _Forcing:
    """Per-sample forcing of one run: harmonic point forces, base acceleration, impulses and
    the pluck's hold (see :func:`run_simulation`)."""

    harmonic: list[Any]  # the harmonic excitation entries
    harmonic_ctrl: np.ndarray  # (samples, harmonic) force amplitudes, N
    accel: np.ndarray  # (samples,) base acceleration, m/s^2 (zeros without ambient)
    base_vector: np.ndarray | None  # generalized force of a unit base acceleration (ambient only)
    impulses: dict[int, np.ndarray]  # sample -> velocity jump of the joints
    hold_until: int  # the pluck holds the beam up to this sample (-1: no pluck)
    hold_qpos: np.ndarray  # (n,) joint angles of the held pluck shape
    info: list[dict[str, Any]]


def _forcing(cfg: SimConfig, modal: dict[str, Any], rate: float, n_samples: int) -> _Forcing:
    """The excitation of ``cfg`` sampled at ``rate``; forces at mid-interval."""
    t_mid = np.arange(n_samples) / rate + 0.5 * (1.0 / rate)
    info: list[dict[str, Any]] = []
    harmonic = [e for e in cfg.excitation if e.type == "harmonic"]
    harmonic_ctrl = np.zeros((n_samples, len(harmonic)))
    for col, exc in enumerate(harmonic):
        phase = 2 * math.pi * exc.get("freq_hz") * (t_mid - exc.get("start_s"))
        harmonic_ctrl[:, col] = exc.get("amplitude_n") * np.sin(phase) * _window(exc, t_mid)
    ambient = [(k, e) for k, e in enumerate(cfg.excitation) if e.type == "ambient"]
    accel = np.zeros(n_samples)
    for k, exc in ambient:
        accel += _ambient_signal(cfg, exc, rate, n_samples, k) * _window(exc, t_mid)
    if ambient:
        info.append({"type": "ambient", "base_accel_rms_m_s2": float(np.sqrt(np.mean(accel**2)))})
    base_vector = _base_accel_vector(modal["model"]) if ambient else None
    hold_until, hold_qpos = _pluck_hold(cfg, modal, rate, info)
    return _Forcing(harmonic, harmonic_ctrl, accel, base_vector, _impulses(cfg, modal["mass"], rate, n_samples),
                    hold_until, hold_qpos, info)


def _impulses(cfg: SimConfig, mass: np.ndarray, rate: float, n_samples: int) -> dict[int, np.ndarray]:
    """Instantaneous velocity jumps ``dq = M^-1 J^T I`` (linearised about q = 0), by sample."""
    impulses: dict[int, np.ndarray] = {}
    for exc in cfg.excitation:
        if exc.type == "impulse":
            sample = int(math.ceil(exc.get("start_s") * rate - 1e-9))
            if sample < n_samples:
                jump = np.linalg.solve(mass, _lever(cfg.beam, exc.get("height_mm"))) * exc.get("impulse_ns")
                impulses[sample] = impulses.get(sample, 0) + jump
    return impulses


def _pluck_hold(cfg: SimConfig, modal: dict[str, Any], rate: float,
                info: list[dict[str, Any]]) -> tuple[int, np.ndarray]:
    """The pluck: the static shape under a point load, scaled to ``peak_mm`` at the given
    height, held until the release; ``(last held sample or -1, joint angles)``."""
    beam = cfg.beam
    hold_until = -1
    hold_qpos = np.zeros(beam.n_segments)
    for exc in cfg.excitation:
        if exc.type == "pluck":
            lever = _lever(beam, exc.get("load_height_mm") or beam.length_mm)
            shape = np.linalg.solve(modal["spring"] + modal["geometric"], lever)
            node_x, _, _ = _node_displacements(beam, shape)
            at = _point_x(beam, node_x, exc.get("height_mm") or cfg.sensor.height_mm)
            hold_qpos = shape * (exc.get("peak_mm") * 1e-3 / at)
            hold_until = int(math.ceil(exc.get("start_s") * rate - 1e-9))
            info.append({"type": "pluck", "tip_static_mm": float(
                _node_displacements(beam, hold_qpos)[0][-1] * 1e3),
                "equivalent_load_n": float(exc.get("peak_mm") * 1e-3 / at)})
    return hold_until, hold_qpos


class _Progress:
    """A tqdm bar over the samples, advanced every 1000 (no bar when not asked for)."""

    def __init__(self, enabled: bool, n_samples: int, engine: str) -> None:
        self.bar = None
        if enabled:
            from tqdm import tqdm
            self.bar = tqdm(total=n_samples - 1, unit="sample", desc=f"simulate ({engine})", mininterval=0.5,
                            disable=n_samples < (2000 if engine == "mujoco" else 20000))
        self.n_samples = n_samples

    def step(self, i: int) -> None:
        if self.bar is not None and i % 1000 == 0:
            self.bar.update(min(1000, self.n_samples - 1 - self.bar.n))

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _integrate_modal(cfg: SimConfig, modal: dict[str, Any], zeta: np.ndarray, forcing: _Forcing,
                     record_dt: float, n_samples: int, progress: _Progress) -> np.ndarray:
    """The linearised model propagated exactly mode by mode; joint angles (samples, n)."""
    omega, modes, mass = modal["omega"], modal["modes"], modal["mass"]
    n = cfg.beam.n_segments
    transition, zoh = _modal_step_matrices(omega, zeta, record_dt)
    # Modal forcing phi_k^T f for every sample.
    force = forcing.harmonic_ctrl @ np.array([modes.T @ _lever(cfg.beam, e.get("height_mm"))
                                              for e in forcing.harmonic]).reshape(len(forcing.harmonic), n)
    if forcing.base_vector is not None:
        force += np.outer(forcing.accel, modes.T @ forcing.base_vector)
    to_modal = modes.T @ mass  # eta = Phi^T M q (mass-normalised modes)
    disp = to_modal @ forcing.hold_qpos
    vel = np.zeros(n)
    eta = np.zeros((n_samples, n))
    t00, t01 = transition[:, 0, 0], transition[:, 0, 1]
    t10, t11 = transition[:, 1, 0], transition[:, 1, 1]
    b0, b1 = zoh[:, 0], zoh[:, 1]
    for i in range(n_samples):
        if i <= forcing.hold_until:
            disp, vel = to_modal @ forcing.hold_qpos, np.zeros(n)
        if i in forcing.impulses:
            vel = vel + to_modal @ forcing.impulses[i]
        eta[i] = disp
        f_i = force[i]
        disp, vel = t00 * disp + t01 * vel + b0 * f_i, t10 * disp + t11 * vel + b1 * f_i
        progress.step(i)
    return eta @ modes.T


def _integrate_mujoco(cfg: SimConfig, modal: dict[str, Any], zeta: np.ndarray, forcing: _Forcing,
                      n_samples: int, substeps: int, dt: float, exact: int,
                      progress: _Progress) -> np.ndarray:
    """The nonlinear MuJoCo chain, semi-implicit Euler, ``substeps`` steps of ``dt`` per
    sample; joint angles (samples, n)."""
    omega, modes, mass = modal["omega"], modal["modes"], modal["mass"]
    n = cfg.beam.n_segments
    exact = min(exact, n)
    # Stiffness-proportional joint damping for the modes above `exact`; the
    # tendons top the lowest modes up to their exact target.
    beta = 2 * zeta[exact - 1] / omega[exact - 1] if exact < n else 0.0
    from_joints = beta * np.einsum("ik,i,ik->k", modes, np.diag(modal["spring"]), modes)
    values = 2 * zeta[:exact] * omega[:exact] - from_joints[:exact]
    values = np.clip(values, 0.0, None)
    coefs = (mass @ modes[:, :exact]).T
    model = build_model(cfg, damping_coefs=coefs, damping_values=values,
                        base_accel_coefs=forcing.base_vector,
                        force_heights_mm=[e.get("height_mm") for e in forcing.harmonic],
                        timestep_s=dt, integrator="Euler")
    model.dof_damping[:] = beta * np.diag(modal["spring"])
    data = mujoco.MjData(model)
    ctrl = np.column_stack([forcing.harmonic_ctrl]
                           + ([forcing.accel] if forcing.base_vector is not None else []))
    data.qpos[:] = forcing.hold_qpos
    qpos = np.zeros((n_samples, n))
    for i in range(n_samples):
        if i <= forcing.hold_until:
            data.qpos[:] = forcing.hold_qpos
            data.qvel[:] = 0.0
        if i in forcing.impulses:
            data.qvel[:] += forcing.impulses[i]
        qpos[i] = data.qpos
        if i == n_samples - 1:
            break
        if model.nu:
            data.ctrl[:] = ctrl[i]
        mujoco.mj_step(model, data, nstep=substeps)
        progress.step(i)
    return qpos


def run_simulation(cfg: SimConfig | Mapping[str, Any] | None = None, *,
                   record_rate_hz: float | None = None, engine: str | None = None,
                   stability_margin: float | None = None, exact_damped_modes: int | None = None,
                   progress: bool = False) -> SimResult:
    """Simulate the configured excitation; returns hinge angles at the record rate.

    ``engine="mujoco"`` steps the nonlinear MuJoCo chain with the semi-implicit
    Euler integrator; the time step is the largest that divides the record
    interval with ``omega_max dt <= 2 * stability_margin`` for the stiffest chain
    mode (stable below 2; the frequency error at mode k is ``(omega_k dt)^2 / 24``).
    The lowest ``exact_damped_modes`` modes get their damping ratio exactly (one
    damped tendon each); the rest get stiffness-proportional joint damping
    ``beta K`` with ``beta`` chosen so their ratio is at least the last target.
    ``engine="modal"`` propagates the same linearised model (MuJoCo M, springs,
    gravity) exactly mode by mode: the small-deflection limit of the MuJoCo run,
    orders of magnitude faster. Forces are held over each record interval at
    their mid-interval value in both engines.
    """
    cfg = _as_config(cfg)
    engine = engine or cfg.simulation.engine
    margin = stability_margin or cfg.simulation.stability_margin
    exact = exact_damped_modes or cfg.simulation.exact_damped_modes
    if engine not in ("mujoco", "modal"):
        raise ValueError(f"engine must be 'mujoco' or 'modal', got {engine!r}")
    rate = record_rate_hz or max(cfg.sensor.rate_hz, cfg.sensor.shape_rate_hz)
    modal = _dof_modal(cfg)
    omega = modal["omega"]
    zeta = np.array([cfg.damping.ratio(k) for k in range(cfg.beam.n_segments)])
    record_dt = 1.0 / rate
    n_samples = int(round(cfg.duration_s * rate)) + 1
    forcing = _forcing(cfg, modal, rate, n_samples)
    bar = _Progress(progress, n_samples, engine)
    wall0 = time.perf_counter()
    if engine == "modal":
        substeps, dt = 1, record_dt
        qpos = _integrate_modal(cfg, modal, zeta, forcing, record_dt, n_samples, bar)
    else:
        substeps = max(1, math.ceil(record_dt * omega[-1] / (2.0 * margin)))
        dt = record_dt / substeps
        qpos = _integrate_mujoco(cfg, modal, zeta, forcing, n_samples, substeps, dt, exact, bar)
    wall = time.perf_counter() - wall0
    bar.close()
    if not np.all(np.isfinite(qpos)):
        raise FloatingPointError("simulation diverged; lower simulation.stability_margin")
    return SimResult(time_s=np.arange(n_samples) / rate, qpos=qpos, record_rate_hz=rate, timestep_s=dt,
                     substeps=substeps, model_hz=(omega[:6] / (2 * math.pi)).tolist(), wall_s=wall,
                     excitation_info=forcing.info, engine=engine)


def sensor_table(cfg: SimConfig, result: SimResult) -> tuple[list[str], np.ndarray]:
    """Columns and rows of ``sensor.csv`` (time_s, dx_mm, dx_mm_z<height>)."""
    beam = cfg.beam
    step = int(round(result.record_rate_hz / cfg.sensor.rate_hz))
    qpos = result.qpos[::step]
    node_x, _, _ = _node_displacements(beam, qpos)
    columns = ["time_s", "dx_mm"]
    values = [result.time_s[::step], _point_x(beam, node_x, cfg.sensor.height_mm) * 1e3]
    for height in cfg.sensor.extra_heights_mm:
        columns.append(f"dx_mm_z{int(round(height)):04d}")
        values.append(_point_x(beam, node_x, height) * 1e3)
    return columns, np.column_stack(values)


def shape_arrays(cfg: SimConfig, result: SimResult) -> dict[str, np.ndarray]:
    """Arrays of ``shapes.npz`` (see docs/formats.md)."""
    step = int(round(result.record_rate_hz / cfg.sensor.shape_rate_hz))
    x, z, theta = _node_displacements(cfg.beam, result.qpos[::step])
    return {"time_s": result.time_s[::step], "z_mm": node_heights_m(cfg.beam) * 1e3,
            "x_mm": x * 1e3, "z_def_mm": z * 1e3, "theta_rad": theta}


def _write_npz_deterministic(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    # np.savez stamps the current time into the zip entries; fix it so the same
    # config gives the same bytes.
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as archive:
        for name, array in arrays.items():
            buffer = io.BytesIO()
            np.lib.format.write_array(buffer, np.ascontiguousarray(array), allow_pickle=False)
            entry = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            entry.external_attr = 0o644 << 16
            archive.writestr(entry, buffer.getvalue())


def simulate(config: SimConfig | Mapping[str, Any], out_dir: str | Path, *,
             progress: bool = True) -> dict[str, Any]:
    """Simulate and write ``sensor.csv``, ``shapes.npz`` and ``sim.json`` into ``out_dir``.

    Returns the sidecar dict.
    """
    from refflow.io import atomic_path, config_hash, versions, write_json

    raw = dict(config) if isinstance(config, Mapping) else None
    cfg = _as_config(config)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    wall0 = time.perf_counter()
    result = run_simulation(cfg, progress=progress)
    modal = modal_analysis(cfg, n_modes=3)

    columns, table = sensor_table(cfg, result)
    with atomic_path(out / "sensor.csv") as tmp:
        with open(tmp, "w", newline="\n") as handle:
            handle.write(",".join(columns) + "\n")
            fmt = ["%.6f"] + ["%.9f"] * (len(columns) - 1)
            np.savetxt(handle, table, fmt=fmt, delimiter=",")
    with atomic_path(out / "shapes.npz") as tmp:
        _write_npz_deterministic(tmp, shape_arrays(cfg, result))
    wall = time.perf_counter() - wall0

    sim_section = {k: raw[k] for k in STAGE_SECTIONS["sim"] if k in raw} if raw is not None else None
    sidecar = {
        "units": {"time_s": "s", "dx_mm": "mm (world +x, relative to the clamp)",
                  "x_mm": "mm", "z_def_mm": "mm", "z_mm": "mm", "theta_rad": "rad about +y"},
        "files": {"sensor": "sensor.csv", "shapes": "shapes.npz"},
        "model_hz": modal["model_hz"],
        "model_hz_no_gravity": modal["model_hz_no_gravity"],
        "euler_bernoulli_hz": modal["euler_bernoulli_hz"],
        "damping_ratios": modal["damping_ratios"],
        "damping_model": ("modal: C = M Phi diag(2 zeta omega) Phi^T M (mujoco: one damped tendon "
                          "per low mode, stiffness-proportional joint damping above)"),
        "model": {"type": "Hencky bar chain (lumped masses, rotational springs EI/h, clamp 2EI/h)",
                  "n_segments": cfg.beam.n_segments, "timestep_s": result.timestep_s,
                  "substeps_per_sample": result.substeps, "engine": result.engine,
                  "integrator": "Euler (semi-implicit)" if result.engine == "mujoco" else "exact modal",
                  "gravity": cfg.beam.gravity},
        "parameters": json.loads(json.dumps(dataclasses.asdict(cfg), default=list)),
        "excitation_info": result.excitation_info,
        "config_hash": config_hash(sim_section if sim_section is not None
                                   else json.loads(json.dumps(dataclasses.asdict(cfg), default=list))),
        "seed": cfg.seed,
        "versions": versions(),
        "timings": {"simulate_wall_s": result.wall_s, "total_wall_s": wall,
                    "simulated_s_per_wall_s": cfg.duration_s / max(result.wall_s, 1e-9)},
    }
    write_json(out / "sim.json", sidecar)
    return sidecar
