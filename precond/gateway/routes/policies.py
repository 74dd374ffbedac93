"""Trained policies: behaviour cloning of the code model on a tenant's demonstrations (a job on the training
queue, progress and cancel at /jobs/{id}), stored per tenant as numbered versions; `/next-action` names one
with `options.policy: "adapter:<id>"`. Another tenant's policy is a 404, word for word as a missing one."""

from __future__ import annotations

import secrets
from typing import Annotated, Any

from fastapi import APIRouter, Path, Request
from fastapi.responses import Response

from precond.gateway.auth import RATE_LIMITED, CurrentCaller
from precond.gateway.deps import Services, ServicesDep
from precond.gateway.errors import ServiceError
from precond.gateway.middleware import OffloadedBodyRoute
from precond.gateway.routes.operations import ERRORS, Wait, answer
from precond.jobs.queue.payloads import TrainPolicyJob
from precond.store import policies as policy_adapters
from precond.store import tenant_store
from precond.store.tenant_store import POLICIES
from precond_client.schemas import ErrorResponse
from precond_client.schemas.training import PolicyAdapter, PolicyAdapterList, TrainPolicyRequest

router = APIRouter(prefix="/policies", tags=["trained policies"], route_class=OffloadedBodyRoute)
NOT_YOURS = "another tenant's is not found either"
RESPONSES: dict[int | str, dict[str, Any]] = {
    **ERRORS,
    404: {"model": ErrorResponse, "description": f"No such trained policy (or version) of yours: {NOT_YOURS}."},
    409: {"model": ErrorResponse, "description": "Another training stored this policy's next version first "
          "(`conflict`): train again."},
    422: {"model": ErrorResponse, "description": "Malformed body; demonstrations without an action call "
          "(`demonstrations`); `options.steps` over PRECOND_MAX_TRAINING_STEPS; the tenant at its bound of "
          "policies, versions or bytes."},
}
AdapterId = Annotated[str, Path(max_length=100, description="A trained policy's id (`ad_...`).")]
AdapterReference = Annotated[str, Path(max_length=100, description="`id`, or `id@version`.")]


def not_found(reference: str) -> ServiceError:
    return ServiceError(404, f"no trained policy {reference[:80]} of yours ({NOT_YOURS})")


@router.post("", response_model=PolicyAdapter, responses=RESPONSES)
async def train_policy(body: TrainPolicyRequest, request: Request, services: ServicesDep, caller: CurrentCaller,
                       wait: Wait = None) -> Response:
    """Fine-tune the code model on the demonstrations (LoRA behaviour cloning: the loss on their action lines
    and turn ends) and store the adapter as version 1 of a new trained policy of yours. A job on the training
    queue (minutes: about 9 s a step on 2 CPU cores for the embedded model): 200 with the stored policy when
    done within `wait`, else 202 and `/jobs/{id}` (progress per step; DELETE cancels, and a cancelled training
    stores nothing)."""
    return await _train(services, request, caller, body, "ad_" + secrets.token_hex(12), 1, wait)


@router.post("/{adapter_id}/versions", response_model=PolicyAdapter, responses=RESPONSES)
async def retrain_policy(adapter_id: AdapterId, body: TrainPolicyRequest, request: Request, services: ServicesDep,
                         caller: CurrentCaller, wait: Wait = None) -> Response:
    """Train again (new demonstrations, other options) and store the result as the policy's next version; the
    earlier versions stay as they were, and `adapter:<id>` names the new one once it is stored."""
    if policy_adapters.parse_reference(adapter_id) is None or "@" in adapter_id:
        raise not_found(adapter_id)
    latest = await tenant_store.latest(services.redis, POLICIES, caller.tag, adapter_id)
    if latest is None:
        raise not_found(adapter_id)
    return await _train(services, request, caller, body, adapter_id, latest + 1, wait)


async def _train(services: Services, request: Request, caller: CurrentCaller, body: TrainPolicyRequest,
                 adapter_id: str, version: int, wait: float | None) -> Response:
    """Bounds first (steps, versions, the tenant's count of policies), then the job; the worker's store checks
    the bounds again, atomically."""
    settings = services.settings
    if body.options.steps > settings.max_training_steps:
        raise ServiceError(422, f"options.steps: {body.options.steps} steps, over this service's bound of "
                           f"{settings.max_training_steps} (PRECOND_MAX_TRAINING_STEPS)", "invalid_input",
                           field="options.steps")
    if version > settings.max_policy_versions:
        raise ServiceError(422, f"trained policy {adapter_id} has {settings.max_policy_versions} versions, the bound "
                           "(PRECOND_MAX_POLICY_VERSIONS)", "invalid_input")
    if version == 1 and await tenant_store.count(services.redis, POLICIES, caller.tag) >= \
            settings.max_policies_per_tenant:
        raise ServiceError(422, f"you have {settings.max_policies_per_tenant} trained policies, the bound "
                           "(PRECOND_MAX_POLICIES_PER_TENANT): delete one first", "invalid_input")
    job = TrainPolicyJob(request=body, adapter=adapter_id, version=version,
                         max_adapters=settings.max_policies_per_tenant, max_versions=settings.max_policy_versions,
                         max_tenant_bytes=settings.max_policy_bytes_per_tenant)
    return await answer(services, request, caller, "train-policy", job, wait)


@router.get("", response_model=PolicyAdapterList, responses={401: ERRORS[401], 429: RATE_LIMITED})
async def list_policies(services: ServicesDep, caller: CurrentCaller) -> PolicyAdapterList:
    """Your trained policies, newest first: the latest version of each, with what trained it."""
    adapters, used = await policy_adapters.listed(services.redis, caller.tag)
    return PolicyAdapterList(adapters=adapters, bytes=used)


@router.get("/{reference}", response_model=PolicyAdapter,
            responses={401: ERRORS[401], 404: RESPONSES[404], 429: RATE_LIMITED})
async def get_policy(reference: AdapterReference, services: ServicesDep, caller: CurrentCaller) -> PolicyAdapter:
    """The latest version (`id`) or a given one (`id@version`): what trained it (losses, seconds, steps, the
    base model) and the calls it knows."""
    found = await policy_adapters.get(services.redis, caller.tag, reference)
    if found is None:
        raise not_found(reference)
    return found


@router.delete("/{adapter_id}", status_code=204,
               responses={401: ERRORS[401], 404: RESPONSES[404], 429: RATE_LIMITED})
async def delete_policy(adapter_id: AdapterId, services: ServicesDep, caller: CurrentCaller) -> Response:
    """Delete the policy and all its versions (their bytes go back to your bound). A next action that names it
    afterwards is a 404; one already running finishes with the version it loaded."""
    if policy_adapters.parse_reference(adapter_id) is None or "@" in adapter_id \
            or not await tenant_store.delete(services.redis, POLICIES, caller.tag, adapter_id):
        raise not_found(adapter_id)
    return Response(status_code=204)
