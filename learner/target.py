"""What the learner aims for: the demonstration on the model grid (:class:`DemoTarget`).

A trimmed demonstration (its first sample is t = 0, the command's clock) becomes the target of
every ILC update (:func:`learner.update.ilc_update`): the rope state at the critical time t_c,
the rope states at the pre-collision model steps (the equally weighted objective and the
critical-point fallback) and the demonstration hand on the model grid (the follow-through
term). Built once per run by :meth:`DemoTarget.from_demonstration`.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from flyknot.constants import MODEL_DT
from flyknot.demo import Demonstration
from flyknot.errors import ConfigError, RecordError, check_positive
from flyknot.geometry import readonly, so3_exp, so3_log
from learner.critical_state import MarkerFitParams, local_polyfit_state, markers_state_at
from learner.system_model import model_times

STATE_DIM = 66  # rope state [p_1..p_11, v_1..v_11]
TIME_TOL = 1e-9  # [s] slack when comparing times with the model grid and t_c
_ROT_TOL = 1e-6
_HAND_CACHE_SIZE = 8  # time grids whose hand a target keeps


@dataclass(frozen=True, eq=False)
class DemoTarget:
    """What the learner aims for, on the model grid of the command's clock (0 = start).

    Attributes:
        t_c: Critical time [s], 0 <= t_c < T.
        T: Command duration [s].
        dt: Model step [s]; the grid is :func:`learner.system_model.model_times` (K+1 steps).
        x_c: Demonstration rope state at t_c, [p_1..p_11, v_1..v_11] (66,) [m, m/s].
        hand_p: Demonstration hand position on the grid, (K+1, 3) [m] (demo frame).
        hand_rot: Demonstration hand orientation on the grid, (K+1, 3, 3).
        hand_v: Demonstration hand velocity on the grid, (K+1, 3) [m/s].
        x_pre: Demonstration rope states at the pre-collision steps k = 0..S-1 (t_k <= t_c),
            (S, 66); a row is NaN where the demonstration's markers were lost.
    """

    t_c: float
    T: float
    dt: float
    x_c: np.ndarray
    hand_p: np.ndarray
    hand_rot: np.ndarray
    hand_v: np.ndarray
    x_pre: np.ndarray
    _hand_cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ("T", "dt"):
            v = getattr(self, name)
            if isinstance(v, numbers.Real) and not isinstance(v, bool):
                v = float(v)
            check_positive(name, v)
            object.__setattr__(self, name, v)
        t_c = self.t_c
        if not (isinstance(t_c, numbers.Real) and np.isfinite(t_c) and 0.0 <= t_c < self.T):
            raise ConfigError("t_c", f"must lie in [0, T) = [0, {self.T:g}) s, got {t_c!r}")
        object.__setattr__(self, "t_c", float(t_c))
        k1 = self.t.size
        n_pre = int(np.sum(self.t <= self.t_c + TIME_TOL))
        want = {
            "x_c": (STATE_DIM,),
            "hand_p": (k1, 3),
            "hand_rot": (k1, 3, 3),
            "hand_v": (k1, 3),
            "x_pre": (n_pre, STATE_DIM),
        }
        for name, shape in want.items():
            a = readonly(getattr(self, name))
            if a.shape != shape:
                raise ConfigError(name, f"must have shape {shape}, got {a.shape}")
            finite = np.isfinite(a)
            if name == "x_pre":
                partial = ~(finite.all(axis=1) | (~finite).all(axis=1))
                if partial.any():
                    raise ConfigError(
                        name, f"row {int(np.argmax(partial))} is partly NaN (whole rows only)"
                    )
            elif not finite.all():
                raise ConfigError(name, "must be finite")
            object.__setattr__(self, name, a)
        RtR = np.swapaxes(self.hand_rot, 1, 2) @ self.hand_rot
        dev = float(np.max(np.abs(RtR - np.eye(3))))
        if dev > _ROT_TOL or np.any(np.linalg.det(self.hand_rot) <= 0):
            raise ConfigError(
                "hand_rot", f"must hold rotation matrices (R^T R - I up to {dev:.2g})"
            )

    @property
    def t(self) -> np.ndarray:
        """Model grid, shape (K+1,) [s]."""
        return model_times(self.T, self.dt)

    def hand_at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Demonstration hand at times t, interpolated on the grid.

        p, v piecewise linear; R(t) = R_i Exp(s Log(R_i^T R_{i+1})), s = (t - t_i) / dt
        (geodesic). Times beyond the last grid step hold its value.

        Args:
            t: Times, shape (m,) [s] in [0, T].

        Returns:
            (p (m, 3) [m], R (m, 3, 3), v (m, 3) [m/s]), read-only (kept per times: each
            update of a learning run asks for the same follow-through grid).
        """
        t = np.ascontiguousarray(np.atleast_1d(np.asarray(t, dtype=float)))
        key = (t.shape, t.tobytes())
        if key not in self._hand_cache:
            if len(self._hand_cache) >= _HAND_CACHE_SIZE:
                self._hand_cache.clear()
            self._hand_cache[key] = tuple(readonly(a) for a in self._hand_at(t))
        return self._hand_cache[key]

    def _hand_at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        grid = self.t
        if (
            t.ndim != 1
            or not np.all(np.isfinite(t))
            or t.min() < -TIME_TOL
            or (t.max() > self.T + TIME_TOL)
        ):
            raise ConfigError("t", f"must be finite times in [0, {self.T:g}] s")
        t = np.clip(t, 0.0, grid[-1])
        if grid.size == 1:
            m = t.size
            return (
                np.repeat(self.hand_p, m, 0),
                np.repeat(self.hand_rot, m, 0),
                np.repeat(self.hand_v, m, 0),
            )
        i = np.minimum((t / self.dt).astype(int), grid.size - 2)
        s = np.clip((t - grid[i]) / self.dt, 0.0, 1.0)[:, None]
        p = (1 - s) * self.hand_p[i] + s * self.hand_p[i + 1]
        v = (1 - s) * self.hand_v[i] + s * self.hand_v[i + 1]
        Ri = self.hand_rot[i]
        rel = so3_log(np.swapaxes(Ri, 1, 2) @ self.hand_rot[i + 1])
        R = Ri @ so3_exp(s * rel)
        return p, R, v

    @classmethod
    def from_demonstration(
        cls,
        demo: Demonstration,
        dt: float = MODEL_DT,
        fit: MarkerFitParams | None = None,
    ) -> DemoTarget:
        """Build the target from a trimmed demonstration (its first sample is t = 0).

        T = t[-1] - t[0], t_c on the command clock = demo.t_c - t[0]. On the model grid:
        hand position and velocity by the local polynomial fit of
        :func:`learner.critical_state.local_polyfit_state` (the same rule as the marker
        states), hand orientation by spherical linear interpolation of the quaternions; the
        rope states at t_c and at the pre-collision steps by
        :func:`learner.critical_state.markers_state_at` (NaN rows where markers are lost).

        Args:
            demo: The trimmed demonstration (demo frame, z up).
            dt: Model step [s].
            fit: Marker/hand fit parameters (default :class:`MarkerFitParams()`).

        Returns:
            The target.

        Raises:
            RecordError: if the demonstration's markers are lost at t_c.
            ConfigError: if t_c is not before the end of the demonstration.
        """
        if not isinstance(demo, Demonstration):
            raise ConfigError("demo", f"must be a Demonstration, got {type(demo).__name__}")
        fit = MarkerFitParams() if fit is None else fit
        td = demo.t - demo.t[0]
        T = float(td[-1])
        t_c = float(demo.t_c - demo.t[0])
        if not t_c < T:
            raise ConfigError("demo.t_c", f"must lie before the demonstration's end {T:g} s")
        grid = model_times(T, dt)
        hp = np.empty((grid.size, 3))
        hv = np.empty((grid.size, 3))
        for k, tk in enumerate(grid):
            hp[k], hv[k] = local_polyfit_state(td, demo.hand_pos, float(tk), fit)
        rots = Rotation.from_quat(np.asarray(demo.hand_quat), scalar_first=True)
        hR = Slerp(td, rots)(grid).as_matrix()
        p, v = markers_state_at(td, demo.markers, t_c, fit)
        x_c = np.concatenate([p.ravel(), v.ravel()])
        pre = grid[grid <= t_c + TIME_TOL]
        x_pre = np.full((pre.size, STATE_DIM), np.nan)
        for k, tk in enumerate(pre):
            try:
                p, v = markers_state_at(td, demo.markers, float(tk), fit)
            except RecordError:
                continue
            x_pre[k] = np.concatenate([p.ravel(), v.ravel()])
        return cls(t_c=t_c, T=T, dt=dt, x_c=x_c, hand_p=hp, hand_rot=hR, hand_v=hv, x_pre=x_pre)


__all__ = ["STATE_DIM", "TIME_TOL", "DemoTarget"]
