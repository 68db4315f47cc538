"""``POST /api/calibrate``: capture θ_home from the person standing in front of the camera now.

Calibration is a configuration change like any other (``retargeting.theta_home``): persisted,
versioned, published and acknowledged, so the safety service needs nothing special for it.
"""

from __future__ import annotations

import time

from fastapi import APIRouter, HTTPException, status

from services.config_api.dependencies import Context, Writer
from services.config_api.models import RETARGET_FIELDS, CalibrateResponse, ErrorResponse
from services.config_api.routers import WRITE_ERRORS
from shared.names import POSE_ANGLE_NAMES

router = APIRouter(prefix="/api", tags=["calibration"])


@router.post(
    "/calibrate",
    response_model=CalibrateResponse,
    responses={**WRITE_ERRORS, 409: {"model": ErrorResponse, "description": "no fresh, complete human pose to capture"}},
)
async def calibrate(actor: Writer, context: Context) -> CalibrateResponse:
    """Set θ_home to the newest HumanState's pose θ. The person should stand neutral (arms down,
    upright). 409 if no HumanState arrived within ``api.calibrate_max_age_s`` or any angle is invalid."""
    newest = context.link.human.get()
    max_age = context.settings.calibrate_max_age_s
    age = None if newest is None else time.monotonic() - newest.received
    if newest is None or age > max_age:
        seen = "no human state received" if newest is None else f"the newest human state is {age:.2f} s old"
        raise HTTPException(status.HTTP_409_CONFLICT, f"cannot calibrate: {seen} (need one within {max_age:g} s)")
    invalid = [name for name, ok in zip(POSE_ANGLE_NAMES, newest.message.theta_valid) if not ok]
    if invalid:
        raise HTTPException(status.HTTP_409_CONFLICT, f"cannot calibrate: invalid angles {', '.join(invalid)}")
    theta = [float(x) for x in newest.message.theta]
    result = await context.writer.change(lambda _: {RETARGET_FIELDS["theta_home"]: theta}, actor, "calibrate")
    return CalibrateResponse(**result.model_dump(), theta_home=theta, human_age_s=age)
