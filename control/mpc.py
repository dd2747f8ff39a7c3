"""MPC path follower (CasADi, multiple shooting) for the forklift.

Problem, solved every tick in the frame of the current estimated pose (`forklift` frame at solve
time, so the start state is (0, 0, 0, steering) and coordinates stay small):

- states `z_k = (x, y, yaw, steering, v_prev)`, k = 0..N: the kinematic model of `control.model`
  plus the previous speed input, which makes the acceleration limit a per-stage constraint;
  inputs `u_k = (speed, steering_rate)`, k = 0..N-1; RK4 over `dt`; `z_{k+1} = F(z_k, u_k)` as
  equality constraints (multiple shooting), `z_0` fixed to the measured state.
- reference per stage: the path point the speed profile reaches at that time, started from the
  projection of the forklift on the path and its current speed (`SegmentTrack.speed_profile`: edge
  speed limits, lateral acceleration on curves, steering rate, a smooth stop at the segment end,
  accelerating at `plan_accel`); past the end the reference stays at the end pose, speed 0.
- cost: contouring error (across the reference tangent), lag error (along it) and heading error,
  steering against the reference curvature's steering, speed against the reference speed,
  acceleration and steering rate; the last stage weighted `terminal` times.
- constraints: speed within the vehicle's limits and the segment's direction (0..max forward,
  -max..0 reverse), acceleration and deceleration, steering angle and steering rate.
- warm start: the previous solution, moved into the new frame and shifted by the tick's time
  (and the previous multipliers for the SQP solvers).

The command sent is the plan's first speed and steering, corrected for the actuators' first-order
lag (`lag_compensated`): the steering command makes the lagged steering follow the planned rate.

Solver choice, by measurement: `palletpilot bench mpc --controllers mpc --solver S [--codegen]`
(10 routes, ~2,900 solves each, N = 20, dt = 0.1 s, 20 Hz closed loop; a 2-core machine shared
with other work, load 1.2-2.2, so the tails are noisy). Solve wall time per tick in ms, two runs:

    option                                        median      p99          max         failed ticks
    ipopt (MUMPS), warm-started primal            2.9 / 3.1   6.9 / 8.5    13 / 25     0
    ipopt, NLP functions as C (gcc -O2)           2.4 / 2.6   5.9 / 6.0    10 / 14     0
    fatrop (structure_detection auto)             1.1 / 1.3   2.4 / 3.4    7.5 / 12    0
    fatrop, NLP functions as C (gcc -O2)          0.87 / 0.91 1.8 / 2.0    2.8 / 23    0
    sqpmethod + qrqp, exact Hessian, max 20 it    2.9 / 3.0   6.9 / 7.8    635 / 755   8 (braked)
    sqpmethod + qrqp, whole solver as C           2.0 / 2.1   5.2 / 5.6    625 / 736   8
    sqpmethod + osqp                              7.5         17.5         26          0

The SQP variants also tracked worse (lateral max 18 mm against 9.5 mm) and had 8 braked ticks
(unconverged or late solves, with 0.6-0.75 s outliers; likely the 20-iteration cap on the tight 1.5 m
arcs, not analysed further). fatrop, the structure-exploiting interior-point solver, is the
default. Code generation saves about 0.3 ms median and 0.5-1.4 ms at p99 for fatrop, far inside the
10 ms budget, but costs 7-9 s of gcc per problem variant (cached afterwards by content hash in
`~/.cache/palletpilot`) and a C compiler on the vehicle: it does not pay, so it is an option
(`MpcConfig(codegen=True)`, `--codegen`), off by default.

A failed solve (solver status, non-finite output) or one slower than `solve_deadline_s` (wall clock;
None in simulated runs) raises `StepFailed`; the `Follower` base then brakes and, after `max_failures` in a row, raises
`ControlError`.
"""

from __future__ import annotations

import hashlib
import math
import os
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from palletpilot.control.errors import ControlError
from palletpilot.control.follower import (
    Follower,
    FollowerConfig,
    SegmentTrack,
    StepFailed,
    StepInput,
    lag_compensated,
    timed,
)
from palletpilot.control.model import KinematicModel
from palletpilot.control.vehicle import VehicleParams
from palletpilot.geometry import SE2

NZ = 5
"""MPC state size: x, y, yaw, steering, previous speed input."""
NU = 2
"""MPC input size: speed, steering rate."""
NP_STAGE = 5
"""Reference parameters per stage: x, y, yaw, speed, steering."""

SOLVERS = ("ipopt", "fatrop", "sqp-qrqp", "sqp-osqp")


@dataclass(frozen=True)
class MpcWeights:
    """Cost weights (per stage; errors in m and rad, speeds in m/s, rates in rad/s)."""

    contour: float = 400.0
    lag: float = 20.0
    heading: float = 100.0
    steering: float = 1.0
    speed: float = 2.0
    accel: float = 20.0
    steering_rate: float = 1.0
    terminal: float = 30.0


@dataclass
class MpcConfig:
    """MPC settings: horizon (steps of `dt` s), solver, weights, deadline."""

    horizon: int = 20
    dt: float = 0.1
    solver: str = "fatrop"
    codegen: bool = False
    """Generate C for the solver and compile it with the system C compiler (`cc`), cached."""
    cache_dir: str | None = None
    """Where compiled solvers are kept (default: `$XDG_CACHE_HOME/palletpilot` or `~/.cache/palletpilot`)."""
    max_iter: int = 20
    solve_deadline_s: float | None = 0.04
    """A solve slower than this (s, wall clock) is a failure: the command would be late. None: no
    deadline, for simulated time, where the simulated vehicle waits for the solve (a loaded machine
    must not change a seeded run); the solve times are still logged."""
    weights: MpcWeights = MpcWeights()


def _state_cost(z: ca.SX, ref: ca.SX, w: MpcWeights, scale: float) -> ca.SX:
    """Cost of a state z against its reference (x, y, yaw, speed, steering): contouring, lag, heading, steering."""
    c, s = ca.cos(ref[2]), ca.sin(ref[2])
    dx, dy = z[0] - ref[0], z[1] - ref[1]
    e_contour = -s * dx + c * dy
    e_lag = c * dx + s * dy
    e_heading = z[2] - ref[2]
    return scale * (
        w.contour * e_contour**2 + w.lag * e_lag**2 + w.heading * e_heading**2 + w.steering * (z[3] - ref[4]) ** 2
    )


def build_nlp(model: KinematicModel, config: MpcConfig) -> dict[str, ca.SX]:
    """The NLP (`x`, `p`, `f`, `g`) of the MPC; variables interleaved stage by stage `z_0, u_0, z_1, ...`.

    `p` = (z_0 (5), then per stage k = 1..N: reference x, y, yaw, speed of u_{k-1}, steering).
    `g` = (z_0 - p_z0 (5); then per stage k = 0..N-1: z_{k+1} - F(z_k, u_k) (5), u_k speed - v_prev_k (1)).
    """
    n, dt, w = config.horizon, config.dt, config.weights
    z_sym, u_sym = ca.SX.sym("z", NZ), ca.SX.sym("u", NU)
    z_next = ca.vertcat(model.rk4(z_sym[:4], u_sym, dt), u_sym[0])
    f_step = ca.Function("F", [z_sym, u_sym], [z_next])
    p = ca.SX.sym("p", NZ + NP_STAGE * n)
    zs = [ca.SX.sym(f"z{k}", NZ) for k in range(n + 1)]
    us = [ca.SX.sym(f"u{k}", NU) for k in range(n)]
    w_vars, g, f = [], [zs[0] - p[:NZ]], ca.SX(0)
    for k in range(n):
        w_vars += [zs[k], us[k]]
        ref = p[NZ + NP_STAGE * k : NZ + NP_STAGE * (k + 1)]
        last = k == n - 1
        # Input cost of u_k and state cost of z_{k+1} against the reference of stage k + 1.
        f += w.speed * (us[k][0] - ref[3]) ** 2 + w.accel * (us[k][0] - zs[k][4]) ** 2
        f += w.steering_rate * us[k][1] ** 2
        f += _state_cost(zs[k + 1], ref, w, w.terminal if last else 1.0)
        g += [zs[k + 1] - f_step(zs[k], us[k]), us[k][0] - zs[k][4]]
    w_vars.append(zs[n])
    return {"x": ca.vertcat(*w_vars), "p": p, "f": f, "g": ca.vertcat(*g)}


def _cache_dir(config: MpcConfig) -> Path:
    if config.cache_dir:
        return Path(config.cache_dir)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "palletpilot"


def _compile_cached(source: bytes, config: MpcConfig) -> Path:
    """Compile generated C with the system compiler (-O2) into a shared library cached by content hash."""
    key = hashlib.sha256(source + ca.__version__.encode()).hexdigest()[:16]  # type: ignore[attr-defined]  # not in stubs
    cache = _cache_dir(config)
    lib = cache / f"mpc_{key}.so"
    if lib.exists():
        return lib
    cache.mkdir(parents=True, exist_ok=True)
    c_file = cache / f"mpc_{key}.c"
    c_file.write_bytes(source)
    compiler = os.environ.get("CC", "cc")
    tmp_lib = cache / f"mpc_{key}.{os.getpid()}.so"
    cmd = [compiler, "-O2", "-fPIC", "-shared", str(c_file), "-o", str(tmp_lib), "-lm"]
    try:
        subprocess.run(cmd, check=True, capture_output=True, text=True, timeout=600)
    except subprocess.CalledProcessError as exc:
        first = next((line for line in exc.stderr.splitlines() if "error" in line), exc.stderr.strip()[:200])
        raise ControlError(f"MPC code generation: compiling {c_file} with {compiler} failed: {first}") from None
    except (OSError, subprocess.SubprocessError) as exc:
        raise ControlError(f"MPC code generation: compiling {c_file} with {compiler} failed: {exc}") from None
    os.replace(tmp_lib, lib)  # atomic: concurrent builders never load a half-written library
    return lib


def _generate(functions: list[ca.Function]) -> bytes:
    """C source of `functions` (one translation unit)."""
    cg = ca.CodeGenerator("mpc_generated.c", {"with_header": False})
    for fn in functions:
        cg.add(fn)
    with tempfile.TemporaryDirectory() as tmp:
        cg.generate(tmp + os.sep)
        return (Path(tmp) / "mpc_generated.c").read_bytes()


def make_solver(model: KinematicModel, config: MpcConfig) -> ca.Function:
    """The CasADi solver function for the MPC's NLP with the configured solver (see module docstring)."""
    if config.solver not in SOLVERS:
        raise ControlError(f"MPC: unknown solver '{config.solver}' (known: {', '.join(SOLVERS)})")
    try:
        return _make_solver(model, config)
    except RuntimeError as exc:  # CasADi: plugin missing, code generation unsupported, ...
        codegen = " with code generation" if config.codegen else ""
        raise ControlError(f"MPC: cannot build the '{config.solver}' solver{codegen}: {exc}") from None


def _make_solver(model: KinematicModel, config: MpcConfig) -> ca.Function:
    nlp = build_nlp(model, config)
    common = {"print_time": False, "error_on_fail": False}
    n = config.horizon
    opts: dict[str, Any]
    if config.solver == "ipopt":
        opts = {
            **common,
            "ipopt": {
                "print_level": 0,
                "max_iter": max(config.max_iter, 50),
                "tol": 1e-6,
                "acceptable_tol": 1e-4,
                "warm_start_init_point": "yes",
                "mu_init": 1e-3,
                "sb": "yes",
            },
        }
        solver = _nlpsol("ipopt", nlp, opts, config)
    elif config.solver == "fatrop":
        opts = {
            **common,
            "structure_detection": "auto",
            "equality": [True] * nlp["g"].shape[0],
            "fatrop": {"print_level": 0, "max_iter": max(config.max_iter, 50), "tol": 1e-6, "mu_init": 1e-2},
        }
        # The acceleration rows are inequalities: one per stage after its 5 dynamics rows.
        eq = [True] * NZ
        for _ in range(n):
            eq += [True] * NZ + [False]
        opts["equality"] = eq
        solver = _nlpsol("fatrop", nlp, opts, config)
    else:
        qp = config.solver.split("-", 1)[1]
        qp_opts: dict = {"print_iter": False, "print_header": False, "error_on_fail": False}
        if qp == "osqp":
            qp_opts = {"osqp": {"verbose": False, "eps_abs": 1e-6, "eps_rel": 1e-6, "polish": True}}
        opts = {
            **common,
            "qpsol": qp,
            "qpsol_options": qp_opts,
            "hessian_approximation": "exact",
            "convexify_strategy": "regularize",
            "max_iter": config.max_iter,
            "tol_pr": 1e-6,
            "tol_du": 1e-4,
            "print_header": False,
            "print_iteration": False,
            "print_status": False,
        }
        solver = ca.nlpsol("mpc", "sqpmethod", nlp, opts)
        if config.codegen:  # qrqp and sqpmethod generate C themselves: the whole solver is compiled
            solver = ca.external("mpc", str(_compile_cached(_generate([solver]), config)))
    return solver


def _nlpsol(plugin: str, nlp: dict[str, ca.SX], opts: dict, config: MpcConfig) -> ca.Function:
    """An nlpsol; with `codegen`, its NLP functions (objective, constraints, derivatives) compiled as C."""
    solver = ca.nlpsol("mpc", plugin, nlp, opts)
    if not config.codegen:
        return solver
    with tempfile.TemporaryDirectory() as tmp:
        cwd = os.getcwd()
        os.chdir(tmp)  # generate_dependencies writes into the working directory only
        try:
            solver.generate_dependencies("mpc_nlp.c", {"with_header": False})
        finally:
            os.chdir(cwd)
        source = (Path(tmp) / "mpc_nlp.c").read_bytes()
    lib = _compile_cached(source, config)
    return ca.nlpsol("mpc", plugin, str(lib), opts)


class MpcFollower(Follower):
    """The MPC path follower; see the module docstring for the problem and `Follower` for the interface."""

    name = "mpc"

    def __init__(
        self, params: VehicleParams, config: MpcConfig | None = None, follower_config: FollowerConfig | None = None
    ) -> None:
        super().__init__(params, follower_config)
        self.mpc = config if config is not None else MpcConfig()
        if self.mpc.horizon < 1 or self.mpc.dt <= 0:
            raise ControlError(f"MPC: bad horizon {self.mpc.horizon} x {self.mpc.dt} s")
        self.solver = make_solver(self.model, self.mpc)
        n = self.mpc.horizon
        self._n_w = NZ * (n + 1) + NU * n
        self._n_g = NZ + (NZ + 1) * n
        self._lbx = np.full(self._n_w, -np.inf)
        self._ubx = np.full(self._n_w, np.inf)
        self._lbg = np.zeros(self._n_g)
        self._ubg = np.zeros(self._n_g)
        self._warm: tuple[np.ndarray, np.ndarray, np.ndarray, SE2, float] | None = None
        self.last_plan: np.ndarray | None = None
        """States of the last accepted plan, (N + 1) x 5, in the frame of the pose it was solved at."""

    # -- layout helpers -----------------------------------------------------------------
    def _z_index(self, k: int) -> int:
        return (NZ + NU) * k

    def _u_index(self, k: int) -> int:
        return (NZ + NU) * k + NZ

    def _split(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = self.mpc.horizon
        z = np.stack([w[self._z_index(k) : self._z_index(k) + NZ] for k in range(n + 1)])
        u = np.stack([w[self._u_index(k) : self._u_index(k) + NU] for k in range(n)])
        return z, u

    def _join(self, z: np.ndarray, u: np.ndarray) -> np.ndarray:
        w = np.empty(self._n_w)
        for k in range(self.mpc.horizon):
            w[self._z_index(k) : self._z_index(k) + NZ] = z[k]
            w[self._u_index(k) : self._u_index(k) + NU] = u[k]
        w[self._z_index(self.mpc.horizon) :] = z[-1]
        return w

    # -- Follower hooks -----------------------------------------------------------------
    def _start_segment(self, track: SegmentTrack) -> None:
        m, n, dt = self.model, self.mpc.horizon, self.mpc.dt
        if track.direction > 0:
            v_lo, v_hi = 0.0, m.max_speed_forward
            a_lo, a_hi = -m.max_decel * dt, m.max_accel * dt
        else:
            v_lo, v_hi = -m.max_speed_reverse, 0.0
            a_lo, a_hi = -m.max_accel * dt, m.max_decel * dt
        for k in range(n + 1):
            i = self._z_index(k)
            self._lbx[i + 3], self._ubx[i + 3] = -m.max_steering, m.max_steering
            self._lbx[i + 4], self._ubx[i + 4] = v_lo, v_hi
            if k < n:
                j = self._u_index(k)
                self._lbx[j], self._ubx[j] = v_lo, v_hi
                self._lbx[j + 1], self._ubx[j + 1] = -m.max_steering_rate, m.max_steering_rate
        for k in range(n):
            row = NZ + (NZ + 1) * k + NZ
            self._lbg[row], self._ubg[row] = a_lo, a_hi
        self._warm = None

    def reference(self, track: SegmentTrack, s0: float, speed: float) -> np.ndarray:
        """Per-stage reference (N x 5: x, y, yaw, signed speed, steering; world frame) from arc length s0 (m)."""
        n, dt, cfg = self.mpc.horizon, self.mpc.dt, self.config
        s_k, v = np.empty(n), abs(speed)
        v_k = np.empty(n)
        s = max(s0, 0.0)
        for k in range(n):
            v_lim = float(track.profile_at(s))
            v = min(v_lim, v + cfg.plan_accel * dt) if v <= v_lim else max(v_lim, v - self.model.max_decel * dt)
            v_k[k] = v
            s = min(s + v * dt, track.length)
            s_k[k] = s
        x, y, heading, kappa = track.sample(s_k)
        return np.column_stack([x, y, heading, track.direction * v_k, self.model.steering_for_curvature(kappa)])

    def _initial_guess(self, z0: np.ndarray, ref_local: np.ndarray, pose: SE2, t: float) -> np.ndarray:
        n, dt = self.mpc.horizon, self.mpc.dt
        if self._warm is not None:
            w_prev, _, _, pose_prev, t_prev = self._warm
            z, u = self._split(w_prev)
            T = pose.inv() @ pose_prev  # previous solve frame seen from the new one
            c, s = math.cos(T.yaw), math.sin(T.yaw)
            xy = z[:, :2] @ np.array([[c, s], [-s, c]]) + np.array([T.x, T.y])
            z = np.column_stack([xy, z[:, 2] + T.yaw, z[:, 3:]])
            shift = float(np.clip(t - t_prev, 0.0, dt * n))
            times = np.arange(n + 1) * dt + shift
            grid = np.arange(n + 1) * dt
            z = np.column_stack([np.interp(times, grid, z[:, i]) for i in range(NZ)])
            u = np.column_stack([np.interp(times[:-1], grid[:-1], u[:, i]) for i in range(NU)])
            z[0] = z0
            return self._join(z, u)
        z = np.zeros((n + 1, NZ))
        z[0] = z0
        z[1:, :3] = ref_local[:, :3]
        z[1:, 3] = z0[3]
        z[1:, 4] = ref_local[:, 3]
        u = np.column_stack([ref_local[:, 3], np.zeros(n)])
        return self._join(z, u)

    def _control(self, track: SegmentTrack, step: StepInput) -> tuple[float, float]:
        m = self.model
        pose = step.pose
        ref = self.reference(track, step.s, step.speed)
        # Reference into the frame of the current pose; headings unwrapped around the current yaw.
        T = pose.inv()
        c, s = math.cos(T.yaw), math.sin(T.yaw)
        xy = ref[:, :2] @ np.array([[c, s], [-s, c]]) + np.array([T.x, T.y])
        yaw0 = math.remainder(ref[0, 2] - pose.yaw, 2 * math.pi)
        yaw = yaw0 + (ref[:, 2] - ref[0, 2])
        ref_local = np.column_stack([xy, yaw, ref[:, 3], ref[:, 4]])

        lo, hi = (0.0, m.max_speed_forward) if track.direction > 0 else (-m.max_speed_reverse, 0.0)
        v_meas = float(np.clip(step.speed, lo, hi))
        steer = float(np.clip(step.steering, -m.max_steering, m.max_steering))
        z0 = np.array([0.0, 0.0, 0.0, steer, v_meas])
        params = np.concatenate([z0, ref_local.reshape(-1)])
        x0 = self._initial_guess(z0, ref_local, pose, step.t)
        args = {
            "x0": x0,
            "p": params,
            "lbx": self._lbx,
            "ubx": self._ubx,
            "lbg": self._lbg,
            "ubg": self._ubg,
        }
        if self._warm is not None and self.mpc.solver.startswith("sqp"):
            args["lam_x0"], args["lam_g0"] = self._warm[1], self._warm[2]

        t0 = timed()
        try:
            sol = self.solver(**args)
        except RuntimeError as exc:
            self._warm = None
            raise StepFailed(f"solver error: {exc}") from None
        elapsed = timed() - t0
        self.log.solve_s.append(elapsed)
        ok = self._solve_ok()
        w = np.asarray(sol["x"]).reshape(-1)
        if not ok or not np.all(np.isfinite(w)):
            self._warm = None
            raise StepFailed(f"solver did not converge ({self._status_text()})")
        if self.mpc.solve_deadline_s is not None and elapsed > self.mpc.solve_deadline_s:
            raise StepFailed(f"late solve: {elapsed * 1e3:.1f} ms > {self.mpc.solve_deadline_s * 1e3:.0f} ms")
        # Constraint check on the returned plan (an unchecked command never leaves).
        g = np.asarray(sol["g"]).reshape(-1)
        viol = max(
            float(np.max(self._lbg - g)),
            float(np.max(g - self._ubg)),
            float(np.max(self._lbx - w)),
            float(np.max(w - self._ubx)),
            0.0,
        )
        if viol > 1e-3:
            self._warm = None
            raise StepFailed(f"plan violates its constraints by {viol:.2e}")
        self._warm = (w, np.asarray(sol["lam_x"]).reshape(-1), np.asarray(sol["lam_g"]).reshape(-1), pose, step.t)
        z, u = self._split(w)
        self.last_plan = z
        dt_tick = self.config.control_dt  # the command holds until the next tick
        steer_target = steer + u[0, 1] * dt_tick
        steer_cmd = lag_compensated(step.steering, steer_target, m.actuator_lag, dt_tick)
        speed_cmd = lag_compensated(step.speed, float(u[0, 0]), m.actuator_lag, dt_tick)
        # Never command past the plan's own limits because of the lag correction.
        speed_cmd = float(np.clip(speed_cmd, lo, hi))
        return speed_cmd, steer_cmd

    @property
    def _external(self) -> bool:
        """True for a fully generated solver (no stats): the SQP solvers with `codegen`."""
        return self.mpc.codegen and self.mpc.solver.startswith("sqp")

    def _solve_ok(self) -> bool:
        if self._external:
            return True  # generated solvers report no stats; the constraint check below decides
        stats = self.solver.stats()
        if stats.get("success", False):
            return True
        status = str(stats.get("return_status", ""))
        # An SQP iteration cap with a feasible iterate is usable: its constraints are checked below.
        return status in {"Maximum_Iterations_Exceeded", "Solved_To_Acceptable_Level"}

    def _status_text(self) -> str:
        if self._external:
            return "generated solver"
        return str(self.solver.stats().get("return_status", "unknown"))
