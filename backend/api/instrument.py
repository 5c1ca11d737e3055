"""The instrument: its state, and on the simulated one its truth and fault injection."""

from __future__ import annotations

import math
from typing import Annotated, Literal

from fastapi import APIRouter, HTTPException, Query, Response
from sqlalchemy import select
from sqlalchemy.orm import Session

from backend.api.deps import OperatorDep, ServicesDep
from backend.api.responses import NPY, npy_response
from backend.api.schemas import InstrumentOut, SimFaultIn
from backend.db.models import Run
from backend.services import Services
from backend.viewer_access import COOKIE, viewer_key
from hardware.sim.instrument import SimulatedAFM

router = APIRouter(prefix="/api/instrument", tags=["instrument"])

#: Largest truth grid served at once (points).
MAX_TRUTH_POINTS = 4096 * 4096
#: Half side of the region the truth route covers (the stage's travel), metres.
SAMPLE_EXTENT = 12e-3
#: How far a ``no_surface`` fault lowers the simulated sample, metres (beyond any landing).
NO_SURFACE_DROP = 1e-3
#: How far a ``crash`` fault lifts the sample mid-line, metres (a step far beyond the loop).
CRASH_JUMP = 100e-9


@router.get("", response_model=InstrumentOut)
async def instrument(services: ServicesDep) -> Response:
    """State, positions (metres), frequency shift (Hz) and whether it is in the safe state
    (read at most every 0.1 s, however many clients ask)."""
    body, version = services.status.instrument()
    if body is None:
        body = await services.status.render(
            ("instrument", version), lambda: _render_instrument(services)
        )
        services.status.keep_instrument(version, body)
    return Response(body, media_type="application/json")


def _render_instrument(services: Services) -> bytes:
    with services.sessions() as session:
        return _instrument(services, session).model_dump_json().encode()


def _instrument(services: Services, session: Session) -> InstrumentOut:
    m = services.microscope
    status = services.runner.instrument_status()
    fault_run = session.scalars(select(Run).where(Run.state == "fault")).first()
    fault = fault_run.id if fault_run is not None else None
    state: Literal["idle", "running", "fault", "error"] = (
        "fault"
        if fault is not None
        else "running"
        if status.get("active_run") is not None
        else "error"
        if "error" in status
        else "idle"
    )
    message = (
        f"run {fault} is in fault ({fault_run.message}): nothing lands until an operator "
        "checks the instrument and resets the run with a note"
        if fault_run is not None
        else status.get("error")
    )
    return InstrumentOut(
        description=m.description,
        simulated=m.simulated,
        state=state,
        active_run=status.get("active_run"),
        safe_state=status.get("safe_state"),
        positions=status.get("positions"),
        frequency_shift=status.get("frequency_shift"),
        loop_engaged=status.get("loop_engaged"),
        fine_range=(m.robot_x.fine_range, m.robot_y.fine_range),
        message=message,
    )


def _sim(services: ServicesDep) -> SimulatedAFM:
    sim = services.microscope.sim
    if sim is None:
        raise HTTPException(
            404, "only the simulated instrument (MOSAIC_INSTRUMENT=sim://) has this"
        )
    return sim


@router.get(
    "/sim/surface",
    response_class=Response,
    responses={200: {"content": {NPY: {}}, "description": "true heights (ny, nx), metres"}},
)
def sim_surface(
    services: ServicesDep,
    x: Annotated[float, Query(description="left edge, metres (sample frame)")],
    y: Annotated[float, Query(description="bottom edge, metres")],
    width: Annotated[float, Query(gt=0, description="metres")],
    height: Annotated[float, Query(gt=0, description="metres")],
    pixel: Annotated[float, Query(gt=0, description="grid pitch, metres")],
    tip: Annotated[
        bool, Query(description="as the tip's apex rides over it: a perfect AFM's image")
    ] = False,
) -> Response:
    """The simulated sample's true heights on a grid from ``(x, y)``: points at
    ``x + j * pixel``, ``y + i * pixel`` covering ``width`` x ``height`` (score a merge
    against it). ``tip=true`` gives the heights dilated by the simulated tip instead."""
    sim = _sim(services)
    values = (x, y, width, height, pixel)
    if not all(math.isfinite(v) for v in values):
        raise HTTPException(422, "x, y, width, height and pixel must be finite numbers of metres")
    if max(abs(x), abs(y), abs(x + width), abs(y + height)) > SAMPLE_EXTENT:
        raise HTTPException(
            422, f"x, y, width, height: stay within ±{SAMPLE_EXTENT * 1e3:g} mm of the origin"
        )
    fx, fy = width / pixel + 1, height / pixel + 1
    if not fx * fy <= MAX_TRUTH_POINTS:
        raise HTTPException(
            422,
            f"{fx:.3g} x {fy:.3g} points is more than {MAX_TRUTH_POINTS}: use a larger pixel "
            "or a smaller area",
        )
    nx, ny = int(fx), int(fy)
    return npy_response(sim.true_heights(x, y, (ny, nx), pixel, tip=tip), "surface.npy")


@router.get("/sim/sem")
def sim_sem(services: ServicesDep) -> dict[str, object]:
    """The simulated SEM's true map over the stage (what the SEM-to-stage calibration must
    recover): its scan's rotation (degrees) and scale against the stage, and the lab position
    of its field's centre (metres)."""
    _sim(services)
    sem = services.microscope.sem
    truth = getattr(sem, "true_map", None)
    if truth is None:
        raise HTTPException(404, "this simulated instrument has no simulated SEM")
    out: dict[str, object] = truth()
    return out


@router.post("/sim/fault", status_code=204)
def sim_fault(body: SimFaultIn, services: ServicesDep, operator: OperatorDep) -> Response:
    """Make the simulated instrument misbehave: a serial link goes silent, answers garbage
    or an error code, or drops; the sample goes out of reach (``no_surface``); the sample
    jumps up under the scanning tip (``crash``: the tip crashes, the run ends in fault); or
    the scans of chosen patches are spoiled (``tip_change``, ``parachute``, ``lost_lines``,
    ``z_jump``). ``none`` heals everything (a crashed tip stays crashed: change it)."""
    sim = _sim(services)
    where = f"on the {body.link} link"
    if body.fault == "none":
        sim.stage_server.inject(None)
        sim.robot_server.inject(None)
        sim.sample_z = 0.0
        sim.jump_next_line(0.0)
        services.runner.rescans.disarm()
    elif body.fault == "no_surface":
        sim.sample_z = -NO_SURFACE_DROP
    elif body.fault == "crash":
        sim.jump_next_line(CRASH_JUMP)
        where = "in the middle of the next line scanned"
    elif body.fault in ("silent", "garbage", "error", "drop"):
        server = sim.stage_server if body.link == "stage" else sim.robot_server
        server.inject(body.fault, code=body.code, count=body.count)
    else:  # a spoiling fault: the schema made sure it names patches
        services.runner.rescans.arm(body.fault, body.patches or [], body.count)
        times = f"{body.count} time(s) each" if body.count else "every try"
        where = f"on patches {body.patches} of the active or next run, {times}"
    services.events.emit(
        "simulation",
        f"simulated fault {body.fault!r} {where} ({operator})",
        data=body.model_dump(),
    )
    return Response(status_code=204)


@router.post("/viewer/session", status_code=204)
def viewer_session(services: ServicesDep, operator: OperatorDep) -> Response:
    """Let this browser open the 3D viewer: a cookie (HttpOnly, SameSite=Strict) that the
    viewer's port checks, with the page's origin, before it sends anything."""
    response = Response(status_code=204)
    response.set_cookie(
        COOKIE,
        viewer_key(services.token),
        httponly=True,
        samesite="strict",
        max_age=7 * 24 * 3600,
    )
    return response


@router.get("/viewer")
def viewer(services: ServicesDep) -> dict[str, object]:
    """Where the 3D viewer listens (its port; the page builds the URL from its own host), what
    it shows and how many browsers it shows it to."""
    v = services.viewer
    if v is None:
        return {
            "enabled": False,
            "port": None,
            "nodes": {"raw": [], "merged": [], "live": []},
            "browsers": 0,
        }
    return {"enabled": True, "port": v.port, "nodes": v.node_names(), "browsers": len(v.views)}
