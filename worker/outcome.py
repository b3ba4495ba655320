"""How an attempt ends, whichever executor ran it: the final report its result calls for."""

from __future__ import annotations

from evaluator.results import EvaluationResult
from internal_api.schemas import LOG_TAIL_LIMIT, REASON_LIMIT, ErrorCause, FinalReport, State


def conclusion(
    result: EvaluationResult, *, log_tail: str = "", detail: str | None = None
) -> FinalReport:
    """Succeeded with a score, or failed (or timed out) with the abort's reason; `detail` adds
    what the platform saw of the policy (how its container ended)."""
    abort = result.abort
    if result.status == "aborted" and abort is not None:
        state = State.TIMED_OUT if abort.kind == "budget_exhausted" else State.FAILED
        reason = (
            abort.reason if not detail or detail in abort.reason else f"{abort.reason}; {detail}"
        )
        return ended(state, reason, result=result, log_tail=abort.log_tail or log_tail)
    return ended(State.SUCCEEDED, f"score {result.score:.3f}", result=result)


def ended(
    state: State,
    reason: str,
    *,
    result: EvaluationResult | None = None,
    log_tail: str = "",
    cause: ErrorCause | None = None,
) -> FinalReport:
    """A final report, with the reason and the log tail cut to what the server keeps."""
    return FinalReport(
        state=state,
        reason=reason[:REASON_LIMIT],
        result=result,
        log_tail=log_tail[-LOG_TAIL_LIMIT:],
        cause=cause,
    )
