"""A reading of the instrument for the status route: positions, frequency shift, loop."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from hardware.microscope import Microscope


def read_instrument(m: Microscope) -> dict[str, Any]:
    """Stage positions and Z extension (metres), Δf (Hz), whether the loop is engaged; the
    safe state as far as the software can tell (loop withdrawn)."""
    z = m.robot_z
    out: dict[str, Any] = {
        "positions": {
            "stage_x": m.stage_x.position(),
            "stage_y": m.stage_y.position(),
            "robot_z_fine_extension": z.fine_extension(),
        },
        "frequency_shift": m.probe.frequency_shift() if m.probe is not None else None,
        "loop_engaged": m.loop.engaged() if m.loop is not None else None,
        "read_at": datetime.now(UTC).isoformat(),
    }
    out["safe_state"] = not out["loop_engaged"]
    return out
