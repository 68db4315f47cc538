"""``/api/config``: read the configuration, change safety and retargeting parameters, history."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends, Query

from services.config_api.dependencies import Context, Writer, allow_read
from services.config_api.models import (
    ChangeResponse,
    ConfigResponse,
    HistoryResponse,
    RetargetParams,
    RetargetPatch,
    SafetyParams,
    SafetyPatch,
)
from services.config_api.routers import READ_ERRORS, READ_OPENAPI, WRITE_ERRORS
from services.config_api.store import public_config

router = APIRouter(prefix="/api/config", tags=["config"])


@router.get("", response_model=ConfigResponse, dependencies=[Depends(allow_read)], responses=READ_ERRORS, openapi_extra=READ_OPENAPI)
async def get_config(context: Context) -> ConfigResponse:
    """The whole configuration (secrets removed), its version, and the safety and retargeting
    parameters under the names PATCH uses."""
    snapshot = context.store.snapshot
    conf = snapshot.config
    return ConfigResponse(
        version=snapshot.version, updated_at=snapshot.updated_at, safety=SafetyParams.from_config(conf),
        retarget=RetargetParams.from_config(conf.retargeting), config=public_config(conf),
    )


@router.patch("/safety", response_model=ChangeResponse, responses=WRITE_ERRORS)
async def patch_safety(patch: SafetyPatch, actor: Writer, context: Context) -> ChangeResponse:
    """Change CBF-QP parameters: ``gamma`` γ, ``phi`` φ, ``k`` K, ``w`` (diagonal of W), ``u_min`` /
    ``u_max``, ``dt``, ``enabled_pair_groups``, ``capsule_radii``, ``human_velocity_term``,
    ``human_predict_s`` (the person swept ahead, s; 0: as measured), ``human_standoff_m`` (m within
    which the robot closes on no person capsule; 0: none), ``human_speed_mps`` (m/s of a person the
    robot slows down for near them; 0: off), ``geometry`` (capsule | spheres |
    box), ``sphere_k``, ``on_intrusion`` (stop | retreat | stop_on_give_way), ``intrusion_backout_mps`` (m/s a
    robot capsule backs out of a still person inside it; 0: none), ``feedforward`` (the target's
    velocity fed forward) and ``target_path`` (jump | continuous: q_nom between camera frames).

    The change is validated on the whole configuration (422 names the field; nothing is applied),
    persisted with the next version, published, and the answer waits until the safety service
    reports it applied (``applied: true``) or ``api.ack_timeout_s`` passed (``applied: false``).
    """
    return await context.writer.change(patch.changes, actor, "patch safety")


@router.patch("/retarget", response_model=ChangeResponse, responses=WRITE_ERRORS)
async def patch_retarget(patch: RetargetPatch, actor: Writer, context: Context) -> ChangeResponse:
    """Change the retargeting (paper eq. 2): ``S``, ``b``, ``q_home``, ``theta_home``, ``mirror``;
    validated, persisted, published and acknowledged like PATCH /api/config/safety."""
    return await context.writer.change(lambda _: patch.changes(), actor, "patch retarget")


@router.get("/history", response_model=HistoryResponse, dependencies=[Depends(allow_read)], responses=READ_ERRORS, openapi_extra=READ_OPENAPI)
async def get_history(context: Context, limit: Annotated[int, Query(ge=1, le=10000)] = 20) -> HistoryResponse:
    """The last ``limit`` accepted changes, newest first: version, time, who, client, action, diff."""
    snapshot = context.store.snapshot
    return HistoryResponse(version=snapshot.version, entries=list(reversed(snapshot.history[-limit:])))
