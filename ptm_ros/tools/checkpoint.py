"""Saving and resuming the particle filter of ``ptm-run`` (``--autosave/--resume``, issue #8):
:class:`RunCheckpoint`.

The state file holds the filter session's state (:meth:`ptm_ros.session.FilterSession.state_dict`: the
filter, the registration cache and its counters, :data:`~ptm_ros.session.SESSION_STATE_SCHEMA`) and meta
data (:func:`run_state_meta`). A run resumes from its own state file or from the ``topology_filter``
node's (:func:`session_state_of`) once :func:`check_state_config` (the same configuration) and
:func:`check_run_state` (its visits the first ones extracted now) accept it.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ptm_ros.config import PtmConfig
from ptm_ros.configio import to_dict
from ptm_ros.errors import ConfigError, DataError
from ptm_ros.model.visits import Visit
from ptm_ros.nodes.filter_inbox import NODE_NAME, NODE_STATE_SCHEMA
from ptm_ros.session import RUN_STATE_TOOL, SESSION_STATE_SCHEMA, FilterSession


@dataclass(frozen=True)
class RunCheckpoint:
    """Saving and resuming :func:`run_offline`'s RBPF (``ptm-run --autosave/--resume``, issue #8).

    Attributes:
        path: the state file (:func:`ptm_ros.inference.persistence.save_filter_state`, written atomically).
        every: save after every ``every``-th visit and after the last one; 0: never save.
        resume: continue from ``path`` when it exists, once :func:`check_run_state` accepts it (else
            start afresh).
    """

    path: Path
    every: int = 0
    resume: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "path", Path(self.path))
        if isinstance(self.every, bool) or not isinstance(self.every, int) or self.every < 0:
            msg = f"RunCheckpoint.every must be an integer >= 0 (visits between saves), got {self.every!r}"
            raise ConfigError(msg)
        if self.every == 0 and not self.resume:
            msg = "RunCheckpoint neither saves (every >= 1) nor resumes: nothing to do"
            raise ConfigError(msg)


def run_state_meta(used: PtmConfig, bag: Path, visits: Sequence[Visit]) -> dict[str, Any]:
    """What :func:`run_offline`'s state file records about its run: the configuration used (as written
    to ``config.yaml``), the bag, the number of visits and their fingerprint."""
    from ptm_ros.inference.persistence import visits_fingerprint

    return {
        "tool": RUN_STATE_TOOL,
        "config": to_dict(used),
        "bag": str(bag),
        "n_visits": len(visits),
        "visits_sha256": visits_fingerprint(visits),
    }


def check_state_config(meta: Mapping[str, Any], used: PtmConfig, path: Path) -> None:
    """Refuse a state file that neither ``ptm-run`` nor the ``topology_filter`` node wrote, or that was
    written with another configuration.

    Raises:
        DataError: written by another program.
        ConfigError: made with another configuration (the differing parameters are named).
    """
    from ptm_ros.inference.persistence import differences

    if meta.get("tool") != RUN_STATE_TOOL and meta.get("node") != NODE_NAME:
        writer = meta.get("tool") or meta.get("node") or "an unknown program"
        msg = f"cannot resume from {path}: written by {writer}, not {RUN_STATE_TOOL} or the {NODE_NAME} node"
        raise DataError(msg)
    if not isinstance(meta.get("config"), Mapping):
        msg = f"cannot resume from {path}: its meta data lack the configuration"
        raise DataError(msg)
    diff = differences(meta["config"], to_dict(used))
    if diff:
        more = f" and {len(diff) - 5} more" if len(diff) > 5 else ""
        msg = (
            f"cannot resume from {path}: it was made with other parameters (differing: "
            f"{', '.join(diff[:5])}{more}); use the same ones, or start afresh without resuming"
        )
        raise ConfigError(msg)


def session_state_of(state: Mapping[str, Any], path: Path) -> Mapping[str, Any]:
    """The filter session's state in a state file: the file's content for ``ptm-run``'s, its ``session``
    for the ``topology_filter`` node's (one session schema, :data:`~ptm_ros.session.SESSION_STATE_SCHEMA`).

    Raises:
        DataError: a node state without a session.
    """
    if state.get("schema") != NODE_STATE_SCHEMA:
        return state
    session = state.get("session")
    if not isinstance(session, Mapping):
        msg = f"cannot resume from {path}: a {NODE_NAME} state without its filter session"
        raise DataError(msg)
    return session


def check_run_state(
    state: Mapping[str, Any], meta: Mapping[str, Any], visits: Sequence[Visit], path: Path
) -> list[Visit]:
    """Check that a state belongs to this run: its saved visits equal to the first ones extracted now
    (extraction is deterministic, offline and in the detector node alike); for ``ptm-run``'s own state
    also the same number of visits and the same visit fingerprint.

    Returns:
        The saved visits.

    Raises:
        DataError: another run's state, or a malformed one.
    """
    from ptm_ros.inference.persistence import first_different_visit, visit_from_state, visits_fingerprint

    where = f"cannot resume from {path}"
    if meta.get("tool") == RUN_STATE_TOOL:  # ptm-run's own state also records the whole run's visits
        if meta.get("n_visits") != len(visits):
            msg = (
                f"{where}: it belongs to a run of {meta.get('n_visits')} landmark visits, this one has "
                f"{len(visits)} (another bag or detector?)"
            )
            raise DataError(msg)
        if meta.get("visits_sha256") != visits_fingerprint(visits):
            msg = f"{where}: its visits differ from this bag's (another bag?)"
            raise DataError(msg)
    if state.get("schema") != SESSION_STATE_SCHEMA:
        schema = state.get("schema")
        msg = f"{where}: not a filter session state (schema {schema!r}, not {SESSION_STATE_SCHEMA!r})"
        raise DataError(msg)
    try:
        saved = [visit_from_state(d) for d in state["visits"]]
    except (KeyError, TypeError) as err:
        msg = f"{where}: malformed state ({type(err).__name__}: {err})"
        raise DataError(msg) from err
    if len(saved) > len(visits):
        msg = f"{where}: it holds {len(saved)} visits, this run has {len(visits)} (another bag?)"
        raise DataError(msg)
    k = first_different_visit(saved, visits)
    if k is not None:
        msg = f"{where}: its visit {k} differs from this run's"
        raise DataError(msg)
    return saved


def _load_run_state(
    checkpoint: RunCheckpoint, log: Callable[[str], None] | None
) -> tuple[dict[str, Any], dict[str, Any]] | None:
    """``(state, meta)`` of the checkpoint's file when resuming from an existing one, else None."""
    from ptm_ros.inference.persistence import load_filter_state

    if not checkpoint.resume:
        return None
    if not checkpoint.path.exists():
        if log is not None:
            log(f"no state file {checkpoint.path} yet: starting afresh")
        return None
    return load_filter_state(checkpoint.path)


def _checkpoint(
    session: FilterSession,
    checkpoint: RunCheckpoint,
    saved: tuple[dict[str, Any], dict[str, Any]] | None,
    *,
    meta: dict[str, Any],
    visits: Sequence[Visit],
) -> tuple[int, Callable[[FilterSession], None] | None]:
    """Restore ``session`` from a saved state (checked against this run's ``visits``); the number of
    visits restored, and the saver of the session's state (:data:`~ptm_ros.session.SESSION_STATE_SCHEMA`,
    with ``meta``) that ``checkpoint`` asks for (None: it only resumes)."""
    from ptm_ros.inference.persistence import save_filter_state

    resumed = 0
    if saved is not None:
        content, saved_meta = saved
        state = session_state_of(content, checkpoint.path)
        resumed = len(check_run_state(state, saved_meta, visits, checkpoint.path))
        session.load_state(state)

    def save(s: FilterSession) -> None:
        checkpoint.path.parent.mkdir(parents=True, exist_ok=True)
        save_filter_state(checkpoint.path, s.state_dict(), meta=meta)

    return resumed, (save if checkpoint.every else None)
