"""``/v1/jobs/{job_id}/deliveries``: a job's callback and every try at delivering it."""

from __future__ import annotations

from fastapi import APIRouter
from sqlalchemy import select

from service.api.deps import DbDep
from service.api.problems import not_found, operation
from service.models import TERMINAL_STATUSES, CallbackAttempt, CallbackDelivery, Job
from service.schemas import DbId, DeliveriesOut, DeliveryAttemptOut

router = APIRouter(prefix="/jobs", tags=["jobs"])


@operation(
    router.get, "/{job_id}/deliveries", "Read a job's callback deliveries", (404,),
    response_model=DeliveriesOut,
    description="The state of the job's callback (none, waiting for the job to end, "
    "pending, delivered, failed) and every try: when, how long, the receiver's status code "
    "and what went wrong. A callback is a POST of compact JSON (job_id, state: succeeded, "
    "failed, cancelled or aborted, status, error, job_url, result_url, finished_at) with "
    "`X-Regtree-Timestamp` (Unix seconds) and `X-Regtree-Signature: sha256=<hex "
    "HMAC-SHA256 of '<timestamp>.<body>' keyed with the setting callback_secret>`; check "
    "both, and refuse an old timestamp. Any 2xx is a delivery; anything else is tried again "
    "after an exponential backoff, up to the setting callback_max_attempts.",
)
def get_deliveries(job_id: DbId, db: DbDep) -> DeliveriesOut:
    with db.read() as session:
        job = session.get(Job, job_id)
        if job is None:
            raise not_found("job", job_id)
        delivery = session.get(CallbackDelivery, job_id)
        rows = session.scalars(
            select(CallbackAttempt)
            .where(CallbackAttempt.job_id == job_id)
            .order_by(CallbackAttempt.attempt, CallbackAttempt.id)
        ).all()
        items = [DeliveryAttemptOut.model_validate(r, from_attributes=True) for r in rows]
        if delivery is None:
            waiting = job.callback_url and job.status not in TERMINAL_STATUSES
            return DeliveriesOut(
                job_id=job_id,
                callback_url=job.callback_url,
                state="waiting" if waiting else "none",
                attempts=0,
                max_attempts=None,
                next_attempt_at=None,
                items=items,
            )
        pending = delivery.state == "pending"
        return DeliveriesOut(
            job_id=job_id,
            callback_url=delivery.url,
            state=delivery.state,  # type: ignore[arg-type]
            attempts=delivery.attempts,
            max_attempts=delivery.max_attempts,
            next_attempt_at=delivery.next_attempt_at if pending else None,
            items=items,
        )
