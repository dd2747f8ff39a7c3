"""Which calibration the Pickup may use: never one with an untrusted axis (README "The adaptive Pickup").

A calibration states the axes it cannot trust (`Calibration.untrusted_axes`, `perception.calibration_io`):
x when the fork tips cannot be trusted (e.g. tapered blades and a forks file without their profile: x may
be 50-150 mm off, and the forks would stop that much short of or past where the estimate says). The rule
(`trusted_axes_only`):

- every axis trusted: the calibration is used as it is, and becomes the truck's trusted calibration
  (`TaskMemory.trusted_calibration`, kept for the whole run);
- untrusted axes, and a trusted calibration of this truck is held (made earlier in this run, or the
  perception service's last good one before this calibration: a calibration file loaded at start seeds
  it; one whose axes were themselves kept from another never counts): when every axis trusted in both
  agrees within `Settings.calibration_mount_tolerance_m` and `_deg` (5 mm on y and z, 0.3 deg on roll,
  pitch and yaw: the mount has not moved; `perception.calibration_io.mount_moved`), the untrusted axes
  are taken from the trusted calibration (`keep_axes`) and the rest stands as measured; the event and the
  task record's `calibration_axis_kept` give the axes, the source and the values used and measured;
- otherwise (none held, or the mount moved) the task fails with `calibration_failed`: the message names
  the axes, why none could be kept and the calibration's own warnings (what to measure); the event and the
  record's `calibration_refused` say the same. It fails at once: a new frame would not change the cause.

A camera that slid along x alone, every other axis unchanged, cannot be told apart from an unmoved one:
measure the blades (`palletpilot forks measure`) so the tips are trusted.

Checks outside the Pickup's calibration (a Delivery's slot check) take `calibration_for_checks`: never
a calibration with an untrusted axis either.

Public API: `trusted_axes_only`, `calibration_for_checks`, `note_trusted`, `LAST_GOOD_SOURCE`.
"""

from __future__ import annotations

from typing import NoReturn

from palletpilot.executor.core.behaviour import Context
from palletpilot.executor.core.errors import CALIBRATION_FAILED, TaskFailed
from palletpilot.perception.calibration_io import Calibration, MountTolerance, keep_axes, mount_moved

LAST_GOOD_SOURCE = "the perception service's last good calibration (a file loaded at start, or made earlier)"
"""The source named for a trusted calibration the Pickup did not see made (`note_trusted`)."""


def note_trusted(ctx: Context, calibration: Calibration | None, source: str) -> None:
    """Hold `calibration` as the truck's newest trusted one (`TaskMemory.trusted_calibration`) when every axis
    of it was measured and trusted (none kept from another); otherwise the one held stays."""
    if calibration is None or calibration.untrusted_axes or calibration.quality.get("kept_axes"):
        return
    if ctx.memory.trusted_calibration is None or ctx.memory.trusted_calibration[0] is not calibration:
        ctx.memory.trusted_calibration = (calibration, source)


def trusted_axes_only(ctx: Context, calibration: Calibration) -> Calibration:
    """The calibration the Pickup uses in place of a new `calibration` (module docstring): itself when
    every axis is trusted, else combined with the trusted one held; `TaskFailed(calibration_failed)` when
    neither can be."""
    if not calibration.untrusted_axes:
        note_trusted(
            ctx, calibration, f"this run's calibration at node '{ctx.memory.at_node}' ({ctx.clock_now():.1f} s)"
        )
        return calibration
    axes = sorted(a.value for a in calibration.untrusted_axes)
    held = ctx.memory.trusted_calibration
    if held is None:
        _refuse(ctx, calibration, axes, "there is no earlier trusted calibration of this truck to keep them from", None)
    reference, source = held
    st = ctx.settings
    moved = mount_moved(
        calibration, reference, MountTolerance(st.calibration_mount_tolerance_m, st.calibration_mount_tolerance_deg)
    )
    if moved:
        why = f"the mount has moved since the trusted calibration: {'; '.join(moved)}"
        _refuse(ctx, calibration, axes, why, source)
    combined = keep_axes(calibration, reference, source)
    kept = {"axes": axes, "source": source, **combined.quality["kept_axes"]}
    ctx.memory.record["calibration_axis_kept"] = kept
    ctx.log("calibration_axis_kept", **kept)
    return combined


def _refuse(ctx: Context, calibration: Calibration, axes: list[str], why: str, source: str | None) -> NoReturn:
    """Record and log the refusal, then fail the task with `calibration_failed` and the warnings' text."""
    ctx.memory.record.setdefault("calibrations", []).append(calibration.to_json())
    refused = {"axes": axes, "why": why, "source": source, "warnings": list(calibration.warnings)}
    ctx.memory.record["calibration_refused"] = refused
    ctx.log("calibration_refused", **refused)
    said = "; ".join(calibration.warnings) or "no warning given"
    raise TaskFailed(
        CALIBRATION_FAILED,
        f"calibration not trusted in {', '.join(axes)}, so the forks do not enter with it: {why}"
        f"{f' ({source})' if source else ''}. The calibration says: {said}",
    )


def calibration_for_checks(ctx: Context) -> Calibration | None:
    """The calibration a camera check may use when the task made none (`ctx.memory.calibration` is None, as in a
    Delivery): the perception service's last good one when every axis is trusted; when it has untrusted
    axes, those kept from the truck's trusted calibration if the mount has not moved (`trusted_axes_only`'s
    rule, nothing logged); the trusted calibration held when the service has none; else None (no camera
    check: the caller relies on its other sensors)."""
    if ctx.memory.calibration is not None:
        return ctx.memory.calibration
    last = ctx.perception.last_good if ctx.perception is not None else None
    if last is not None and not last.untrusted_axes:
        return last
    held = ctx.memory.trusted_calibration
    if held is None:
        return None
    if last is None:
        return held[0]
    st = ctx.settings
    if mount_moved(last, held[0], MountTolerance(st.calibration_mount_tolerance_m, st.calibration_mount_tolerance_deg)):
        return None
    return keep_axes(last, held[0], held[1])
