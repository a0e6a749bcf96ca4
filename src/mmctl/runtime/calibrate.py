"""The daemon's side of `mmctl calibrate tool`: the control socket's ``calibrate``
request and the routine's part of each cycle (:class:`Calibrations`, which holds the
loop's :class:`~mmctl.runtime.driver.LoopRuntime`; composed by
:class:`~mmctl.runtime.daemon.Daemon`).

``{"cmd": "calibrate", "action": "start", "poses": N}`` plans the poses from the arm's
newest sample (on the request's thread: it takes milliseconds), then the loop checks
that the robot is armed, still, not taring, and nobody pushes the handle, and installs
a :class:`~mmctl.control.calibration.ToolCalibration` (refused with a reason
otherwise); the reply says how many poses and how long.  While it runs, the loop's
controller idles (its state held at rest, every fault check as when disarmed) and
:meth:`Calibrations.cycle` sends the routine's speedJ and a zero
base twist instead.  ``"action": "status"`` reports its progress and, once done, the
fit (:func:`~mmctl.control.calibration.fit_tool_load`, computed on the loop in the
cycle that ends it); ``"action": "abort"`` stops it.  An aborted calibration (a push,
the operator's abort, a pose not reached, the base moved) stops the robot like
``disable``: speedStop, zero base velocity, disarmed; a fault or ``disable`` during it
end it the same way.  Nothing is applied to the running daemon: the operator writes
the fit into the configuration (`mmctl calibrate tool --write FILE`) and restarts.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from typing import TYPE_CHECKING

import numpy as np
import structlog

from mmctl.control.calibration import (
    Plan,
    ToolCalibration,
    ToolLoadFit,
    fit_tool_load,
    gravity_direction,
    plan_poses,
)
from mmctl.control.update import Disable
from mmctl.errors import MmctlError
from mmctl.runtime.core import CycleResult
from mmctl.runtime.driver import LoopRuntime
from mmctl.types import Vec, Wrench

log = structlog.get_logger("mmctl.daemon")

#: [rad/s] / [m/s] the robot is still when no joint, wheel-base speed or command exceeds this
STILL_JOINT = 0.01
STILL_BASE = 0.005
#: the range of a request's ``poses``
POSES_RANGE = (4, 50)
_Z3 = np.zeros(3)

if TYPE_CHECKING:
    from mmctl.model.robot import RobotModel


class Calibrations:
    """``calibrate`` requests and the routine's cycle (see the module docstring).  The
    routine itself is the runtime's :attr:`~mmctl.runtime.driver.LoopRuntime.calibration`
    (the loop reads it); its fit is :attr:`fit`."""

    def __init__(self, runtime: LoopRuntime):
        self.rt = runtime
        self.cfg = runtime.cfg
        #: the fit of the newest calibration that finished (None: none yet)
        self.fit: ToolLoadFit | None = None
        self._planner: RobotModel | None = None
        self._planner_lock = threading.Lock()
        runtime.calibration_cycle = self.cycle

    @property
    def current(self) -> ToolCalibration | None:
        """The newest calibration (running or ended), or None."""
        return self.rt.calibration

    def command(self, req: Mapping[str, object]) -> object:
        action = req.get("action", "status")
        if action == "start":
            return self._request(req.get("poses"))
        if action == "status":
            return self.report()
        if action == "abort":
            report, disarmed = self.rt.on_loop(self._abort)
            if disarmed is not None and self.rt.loop.running:
                # the reply once the update has taken the Disable: a status asked right
                # after the abort says disarmed
                try:
                    disarmed.result(self.cfg.daemon.command_timeout)
                except (FutureTimeout, MmctlError) as exc:  # aborted all the same: the
                    # stop went out; the loop that did not take the Disable says why
                    log.warning("calibration_abort_disable_not_taken", error=str(exc))
            return report
        raise MmctlError(f"calibrate: action {action!r}: must be 'start', 'status' or 'abort'")

    def _request(self, poses: object) -> dict[str, object]:
        """Plan on this thread from the newest sample, then start on the loop."""
        cal = self.cfg.sensor.calibration
        n = cal.poses if poses is None else poses
        lo, hi = POSES_RANGE
        if isinstance(n, bool) or not isinstance(n, int) or not lo <= n <= hi:
            raise MmctlError(f"calibrate: poses = {n!r}: must be a whole number within "
                             f"[{lo}, {hi}]")
        last = self.rt.last
        if last is None or not np.isfinite(last.q).all():
            raise MmctlError("refused to calibrate: no arm sample yet")
        self._precheck(last)  # at once, before the planning
        q = last.q.copy()
        caps = self.rt.core.caps
        with self._planner_lock:  # one model per thread: this one for the requests'
            if self._planner is None:
                from mmctl.model.robot import RobotModel

                self._planner = RobotModel(self.cfg.robot)
            clearance = None
            if self.cfg.safety.collision_check:
                from mmctl.model.geometry import BodyModel

                planner = self._planner
                clearance = BodyModel(self.cfg.robot, planner.arm, planner.mount).clearance
            plan = plan_poses(self._planner, q[:6], n, cal, self.cfg.limits,
                              self.cfg.safety.max_condition, float(caps["ee_speed_m_s"] or 0.25),
                              self.cfg.walls.ee_box, clearance,
                              self.cfg.safety.collision_margin)
        started: dict[str, object] = self.rt.on_loop(lambda: self._begin(plan, q))
        return started

    def _precheck(self, last: CycleResult) -> None:
        """MmctlError unless the robot is armed, still, not taring, not calibrating and
        nobody pushes the handle (as the newest cycle saw it)."""
        current = self.rt.calibration
        if current is not None and current.running:
            raise MmctlError("refused to calibrate: a calibration is running "
                             f"({current.progress()['phase']} at pose {current.index + 1})")
        if not self.rt.safety.armed:
            raise MmctlError(f"refused to calibrate: the robot is {self.rt.safety.state.value}; "
                             "it needs to be armed (`mmctl enable`) and still, hands off "
                             "the handle")
        if self.rt.core.taring:
            raise MmctlError("refused to calibrate: a tare is in progress")
        if self.rt.ustate.arm_repeats >= self.cfg.arm.hold_cycles:
            raise MmctlError("refused to calibrate: the arm's samples are not coming in")
        joint = float(np.abs(last.qd[:6]).max())
        base = float(np.hypot(last.qd[6], last.qd[7]))
        cmd = float(np.abs(last.qd_cmd).max())
        if joint > STILL_JOINT or base > STILL_BASE or abs(last.qd[8]) > STILL_JOINT \
                or cmd > STILL_JOINT:
            raise MmctlError(f"refused to calibrate: the robot is moving (joints up to "
                             f"{joint:.3f} rad/s, base {base:.3f} m/s, command up to "
                             f"{cmd:.3f}); it starts from rest: hands off the handle and "
                             "wait (or release the enabling switch)")
        force = float(np.linalg.norm(last.f_h[:3]))
        limit = self.cfg.sensor.calibration.abort_force
        if force > limit:
            raise MmctlError(f"refused to calibrate: {force:.1f} N on the handle (more than "
                             f"sensor.calibration.abort_force {limit:g} N): hands off")

    def _begin(self, plan: Plan, q_planned: Vec) -> dict[str, object]:
        """Loop thread: check again and install the routine."""
        last = self.rt.last
        if last is None:
            raise MmctlError("refused to calibrate: no arm sample yet")
        self._precheck(last)
        moved = float(np.abs(last.q[:6] - q_planned[:6]).max())
        if moved > 0.01:
            raise MmctlError(f"refused to calibrate: the arm moved {moved:.3f} rad while "
                             "the poses were planned; try again")
        cal = self.cfg.sensor.calibration
        w = self.cfg.sensor.wrench
        self.fit = None
        self.rt.calibration = ToolCalibration(plan, cal, (w.handle_mass, np.asarray(w.handle_com)),
                                           self.rt.core.model, last.q[6:9], self.rt.core.clock())
        seconds = plan.duration(cal.settle_time, cal.average_time)
        log.info("calibration_started", poses=len(plan.poses), estimated_s=round(seconds, 1),
                 speeds=[round(s, 3) for s in plan.speeds])
        return {"started": True, "poses": len(plan.poses), "estimated_s": round(seconds, 1),
                "plan": [[round(float(x), 5) for x in p] for p in plan.poses]}

    def _abort(self) -> tuple[dict[str, object], Future[object] | None]:
        """Loop thread: the operator's abort: stop the robot (disarmed); the report and
        the Disable's reply (None: nothing was running)."""
        c = self.rt.calibration
        disarmed = None
        if c is not None and c.running:
            c.abort("aborted by the operator", self.rt.core.clock())
            disarmed = self._stop(c)
        return self.report(), disarmed

    def _stop(self, c: ToolCalibration) -> Future[object]:
        """Loop thread: an aborted routine: speedStop and zero base velocity at once,
        and a :class:`~mmctl.control.update.Disable` into the loop's inbox, so the
        update disarms (as the operator's ``disable`` does; never a state changed
        behind the update's back).  The operator's abort runs before this cycle's
        update, which takes the Disable in the same cycle; an abort the routine finds
        during a cycle is disarmed by the next one, whose update sends no motion."""
        self.rt.send_stop()
        disarmed = self.rt.submit(Disable())
        c.closed = True
        log.warning("calibration_aborted", reason=c.error, pose=c.index + 1,
                    weighed=len(c.samples))
        return disarmed

    def report(self) -> dict[str, object]:
        """Progress of the last calibration; once done, its fit and what it weighed."""
        c = self.rt.calibration
        if c is None:
            return {"phase": "none"}
        out = c.progress()
        w = self.cfg.sensor.wrench
        out["configured"] = {"handle_mass": w.handle_mass, "handle_com": list(w.handle_com)}
        fit = self.fit
        if out["phase"] == "done" and fit is not None:
            out["fit"] = fit.as_dict()
            out["samples"] = [
                {"q": [round(float(x), 5) for x in s.q],
                 "gravity": [round(float(x), 5) for x in gravity_direction(s.rotation)],
                 "wrench": [round(float(x), 5) for x in s.wrench],
                 "std": [round(float(x), 5) for x in s.std], "count": s.n}
                for s in c.samples]
        out["peak_deviation"] = {"force_N": round(c.peak_force, 3),
                                 "torque_Nm": round(c.peak_torque, 4)}
        return out

    def cycle(self, c: ToolCalibration, result: CycleResult | None,
                           wrench: Wrench | None, repeats: int) -> CycleResult | None:
        """Loop thread, after the safety monitor: the routine's command in place of the
        controller's (arm: its speedJ; base: zero), or its end.  ``repeats``: cycles the
        arm's pose has been repeated (0: this cycle's sample)."""
        now = self.rt.core.clock()
        if not self.rt.safety.armed:  # a fault (the stop went out) or disable
            cause = self.rt.safety.latched.value if self.rt.safety.latched else "disable"
            c.abort(f"the robot was disarmed ({cause})", now)
            c.closed = True
            log.warning("calibration_aborted", reason=c.error, pose=c.index + 1,
                        weighed=len(c.samples))
            return result
        if result is None or wrench is None:
            return result
        cmd = c.step(result.q, result.qd, wrench.as_array(), wrench.sequence, now,
                     hold=repeats >= self.cfg.arm.hold_cycles, scaling=self.rt.speed_scaling,
                     pose_new=repeats == 0, sample_age=now - wrench.timestamp,
                     pose_time=self.rt.ustate.arm_time)
        if c.phase == "done":
            self._done(c)
        if c.phase == "aborted":
            self._stop(c)
            return result
        return result._replace(qd_arm=cmd, qd_cmd=np.concatenate((cmd, _Z3)), twist=_Z3)

    def _done(self, c: ToolCalibration) -> None:
        """Loop thread, once: the fit (a 10-column least squares: tens of us)."""
        try:
            fit = fit_tool_load([s.rotation for s in c.samples], [s.wrench for s in c.samples])
        except ValueError as exc:  # (a bug: every pose's numbers are finite)
            c.phase, c.error = "aborted", f"no fit: {exc}"
            return
        self.fit = fit
        c.closed = True
        log.info("calibration_done", seconds=round(float(c.finished or 0) - c.started, 1),
                 mass_kg=round(fit.mass, 4), com_m=[round(float(x), 4) for x in fit.com],
                 residual_force_rms_N=round(fit.residual_force_rms, 4),
                 residual_torque_rms_Nm=round(fit.residual_torque_rms, 5),
                 condition=round(fit.condition, 2), warnings=list(fit.warnings))
