"""The ``topology_filter`` node's logic without rclpy: its input stream, filter session and state file.

:class:`FilterInbox` takes the ``landmark_visits`` messages as text (:meth:`FilterInbox.receive`), keeps
the detector's stream in order (sessions, gaps, duplicates, redelivered visits, end markers; see
:mod:`ptm_ros.nodes.topology_filter` for the rules and counters), feeds the accepted visits to a
:class:`~ptm_ros.session.FilterSession` (the code ``ptm-run`` runs) and saves and restores its state
(:mod:`ptm_ros.inference.persistence`). It logs through any object with
``debug``/``info``/``warning``/``error`` (a node's logger, or :mod:`logging`'s), and tells its caller what to
publish; the node only wires topics, services, parameters and timers around it. Nothing here imports rclpy (a
contract of ``.importlinter``), so the behaviour is tested without a ROS context.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from pathlib import Path
from typing import Any

from ptm_ros.config import PtmConfig
from ptm_ros.configio import to_dict
from ptm_ros.errors import ConfigError, DataError, PtmError
from ptm_ros.inference.persistence import differences, load_filter_state, save_filter_state
from ptm_ros.inference.rbpf import FilterState
from ptm_ros.model.ptm import Ptm
from ptm_ros.model.visits import Visit, pose_field
from ptm_ros.nodes.logs import Logger, OnceLogger
from ptm_ros.nodes.messages import parse_visit_envelope
from ptm_ros.reporting.figures import ess_fraction
from ptm_ros.session import RUN_STATE_TOOL, SESSION_STATE_SCHEMA, FilterSession

NODE_NAME = "topology_filter"
#: Schema tag of the node's state file content (its ``session`` is a :class:`FilterSession` state).
NODE_STATE_SCHEMA = "ptm_ros.topology_filter_state/1"
MAX_VISIT_GAP = 1000  # visits: a larger jump of the detector's index is a corrupt message
MAX_RETIRED = 64  # finished detector sessions remembered (their late visits never start a new map)
COUNTERS = (
    "messages",
    "accepted",
    "ends",
    "invalid",
    "rejected",
    "duplicates",
    "gaps",
    "implausible",
    "out_of_order",
    "foreign",
    "resets",
    "redelivered",
    "internal_errors",
)
#: Counters that are no problem (the others turn /diagnostics to WARN).
BENIGN = ("messages", "accepted", "ends", "resets", "redelivered")


class Reaction(enum.Enum):
    """What the caller publishes after a message: nothing, the ensemble, or the ensemble with a new
    visit in it (whose doubts are then worth a log line)."""

    NONE = enum.auto()
    PUBLISH = enum.auto()
    NEW_VISIT = enum.auto()


class FilterInbox:
    """The topology filter's visit stream, filter session and state file (see the module docstring).

    Args:
        config: the model and inference configuration (as ``ptm-run``'s).
        logger: where problems and progress are logged.
        refit_max_visits: the session's appearance refits (:class:`FilterSession`).
        frame_id: frame of the visits, recorded in the state's meta data.
        state_file: where :meth:`save_state` writes (None: saving is off).
        autosave_every: save every this many visits (and at the end marker); 0 = off.
    """

    def __init__(
        self,
        config: PtmConfig,
        logger: Logger,
        *,
        refit_max_visits: int = 100,
        frame_id: str = "odom",
        state_file: Path | None = None,
        autosave_every: int = 0,
    ) -> None:
        self.config = config
        self.refit_max_visits = refit_max_visits
        self.frame_id = frame_id
        self.state_file = state_file
        self.autosave_every = autosave_every
        self.session = FilterSession(config, refit_max_visits=refit_max_visits)
        self.counters = dict.fromkeys(COUNTERS, 0)
        self.persistence = {"resumed_visits": 0, "resume_rejected": 0, "saves": 0, "save_failures": 0}
        self.last: FilterState | None = None  # the latest update's diagnostics
        self._logger = logger
        self._log_once = OnceLogger(logger)
        self._next_index: int | None = None  # the detector's index of the next visit (None: any)
        self._end_count: int | None = None  # visits the detector announced at its end
        self._stream: str | None = None  # the detector session of the map's visits
        self._first: tuple[float, tuple[float, float, float]] | None = None  # (stamp, pose) of its visit 0
        self._last_stamp = -math.inf  # stamp of the latest visit in the map
        self._retired: dict[str, int] = {}  # finished detector sessions -> visits they had
        self._resumed: dict[str | None, int] = {}  # detector sessions -> visits restored from state_file
        self._adopt = 0  # visits restored from ptm-run's state, for the detector session delivering them
        self._unsaved = 0  # visits taken since the state was last saved
        self.dirty = False  # anything changed since the state was last saved (visits, end markers, resets)

    # -------------------------------------------------------------------------------- visits

    @property
    def complete(self) -> bool:
        """Whether the detector reported its end and every visit it announced has been consumed."""
        if self._end_count is None:
            return False
        return (self._next_index or 0) >= self._end_count

    def _drop(self, counter: str, message: str) -> None:
        self.counters[counter] += 1
        self._log_once(counter, message)

    def receive(self, text: str) -> Reaction:
        """Take one ``landmark_visits`` message (its JSON text)."""
        self.counters["messages"] += 1
        try:
            item, session = parse_visit_envelope(text)
        except DataError as err:
            self._drop("invalid", f"dropped a malformed landmark_visits message: {err}")
            return Reaction.NONE
        if isinstance(item, int):
            return self._end(item, session)
        return self._add(item, session)

    def _end(self, count: int, session: str | None) -> Reaction:
        if session != self._stream and session in self._resumed:
            self.counters["redelivered"] += 1  # the end of a session restored from state_file
            return Reaction.NONE
        if self._next_index is not None and session != self._stream:
            if count != 0 or session in self._retired:
                self._drop("foreign", f"ignored the end marker of detector session {session!r}")
                return Reaction.NONE
            self._logger.warning(
                f"detector session {session!r} ended without a visit: the map of {self._stream!r} is final"
            )
            count = self._next_index  # a restarted detector found nothing more: the input is over
        if count < (self._next_index or 0):
            self._drop(
                "invalid", f"ignored an end marker of {count} visits: {self._next_index} already arrived"
            )
            return Reaction.NONE
        self._end_count = count
        self.counters["ends"] += 1
        self._logger.info(f"end of visits reported ({count}); {len(self.session.visits)} in the map")
        self.dirty = True
        if self.autosave_every > 0:
            self.autosave()
        return Reaction.PUBLISH

    def _shapes_differ(self, visit: Visit) -> bool:
        """Whether the visit's signature or word histogram differs in length from the map's."""
        for name in ("signature", "words"):
            new = getattr(visit, name)
            old = next((a for v in self.session.visits if (a := getattr(v, name)) is not None), None)
            if new is not None and old is not None and new.shape != old.shape:
                return True
        return False

    def _add(self, visit: Visit, session: str | None) -> Reaction:
        """Consume the detector's visit ``visit.index`` of detector session ``session`` (re-indexed from
        the last reset on; see :mod:`ptm_ros.nodes.topology_filter` for what is dropped)."""
        key = (visit.stamp, visit.pose)
        if self._adopt and session not in self._retired and self._restored(visit.index, key):
            self._stream, self._resumed[session], self._adopt = session, self._adopt, 0
            self._logger.info(
                f"detector session {session!r} delivers the visits of the resumed ptm-run state"
            )
        if self._redelivered(session, visit.index, key):
            self.counters["redelivered"] += 1
            if self.counters["redelivered"] == 1:
                self._logger.info("the detector redelivers visits restored from the state file: skipped")
            return Reaction.NONE
        if self._next_index is not None and session != self._stream:
            if visit.index != 0 or session in self._retired:
                self._drop("foreign", f"dropped visit {visit.index} of another detector session {session!r}")
                return Reaction.NONE
            self._logger.warning(f"detector session {session!r} started: starting a new map")
            self._retire()
            self.reset()
        elif self._next_index is not None and visit.index < self._next_index:
            if visit.index != 0 or session is not None or key == self._first:
                self._drop("duplicates", f"dropped visit {visit.index}: already processed")
                return Reaction.NONE
            self._logger.warning("a different visit 0 arrived: the detector restarted; starting a new map")
            self.reset()
        elif self._next_index is not None and visit.index > self._next_index + MAX_VISIT_GAP:
            self._drop("implausible", f"dropped visit {visit.index}: {self._next_index} was expected")
            return Reaction.NONE
        if visit.stamp < self._last_stamp:
            self._drop("out_of_order", f"dropped visit {visit.index}: older than the map's latest visit")
            return Reaction.NONE
        if self._shapes_differ(visit):
            self._drop("invalid", f"dropped visit {visit.index}: measurements shaped unlike the map's")
            return Reaction.NONE
        expected = visit.index if self._next_index is None else self._next_index
        if visit.index > expected:
            self._drop("gaps", f"visits {expected}..{visit.index - 1} never arrived; continuing without them")
        if self._next_index is None:
            self._stream = session
            self._first = key if visit.index == 0 else None
        self._next_index = visit.index + 1
        self.counters["accepted"] += 1
        n = len(self.session.visits)
        if visit.index != n:
            visit = dataclasses.replace(visit, index=n)
        replays, wall = self.session.replays, self.session.wall_s
        self._unsaved += 1
        self.dirty = True
        try:
            self.last = state = self.session.add(visit)
        except PtmError as err:
            self._drop("rejected", f"the filter rejected visit {visit.index}: {err}")
            self._maybe_autosave()
            return Reaction.PUBLISH if self.complete else Reaction.NONE
        self._last_stamp = visit.stamp
        how = "replayed" if self.session.replays > replays else "updated"
        flt = self.session.filter
        map_mass = max(flt.ptm_weights().values(), default=0.0) if flt is not None else 0.0
        ms = (self.session.wall_s - wall) * 1e3
        self._logger.info(visit_line(visit.index, state, map_mass, how=how, ms=ms))
        self._maybe_autosave()
        return Reaction.NEW_VISIT

    def _redelivered(self, session: str | None, index: int, key: tuple[Any, ...]) -> bool:
        """Whether a visit was restored from the state file (the detector's history delivers it again to
        a resumed filter). Without session ids, a visit 0 unlike the map's is a restart, not a repeat."""
        limit = self._resumed.get(session)
        if limit is None or index >= limit:
            return False
        return not (session is None and index == 0 and key != self._first)

    def _restored(self, index: int, key: tuple[Any, ...]) -> bool:
        """Whether visit ``index`` with ``key`` (stamp, pose) is the map's visit ``index``."""
        visits = self.session.visits
        return index < len(visits) and (visits[index].stamp, visits[index].pose) == key

    def _retire(self) -> None:
        """Remember the current detector session as finished (its late visits never start a new map)."""
        if self._stream is None:
            return
        self._retired[self._stream] = self._next_index or 0
        while len(self._retired) > MAX_RETIRED:
            del self._retired[next(iter(self._retired))]

    def reset(self) -> None:
        """Forget the map: the next visit starts a new one (counted in ``resets``)."""
        self.session.reset()
        self._next_index = self._end_count = self._stream = self._first = self.last = None
        self._last_stamp = -math.inf
        self._adopt = 0
        self.counters["resets"] += 1
        self.dirty = True

    def forget(self) -> int:
        """:meth:`reset` on request (``~/reset``): also the visits restored from the state file start a
        new map when they come again. Returns the number of visits forgotten."""
        n = len(self.session.visits)
        self.reset()
        self._resumed = {}
        return n

    def current_ptm(self) -> Ptm:
        """The ensemble now (an empty PTM before the first visit)."""
        if self.session.filter is None:
            return Ptm(
                landmarks=(), topologies=(), frame_id=self.frame_id, extra={"diagnostics": self.diagnostics()}
            )
        return self.session.to_ptm(frame_id=self.frame_id, diagnostics=self.diagnostics())

    def diagnostics(self) -> dict[str, Any]:
        """Counters reported on /diagnostics and in the graph document."""
        last = self.last
        return {
            "visits": len(self.session.visits),
            "particles": 0 if self.session.filter is None else self.session.filter.n_topologies,
            "ess": 0.0 if last is None else last.ess,
            "update_ms": 0.0 if last is None else last.update_s * 1e3,
            "replays": self.session.replays,
            "registrations": dict(self.session.registrations),
            **self.counters,
            "persistence": dict(self.persistence),
        }

    def problems(self) -> int:
        """Messages dropped for a problem, failed resumes and failed saves (non-zero: WARN)."""
        bad = sum(self.counters[k] for k in COUNTERS if k not in BENIGN)
        return bad + self.persistence["resume_rejected"] + self.persistence["save_failures"]

    # --------------------------------------------------------------------------- persistence

    def state_meta(self) -> dict[str, Any]:
        """What the state file records about how its state was made (checked on resume)."""
        return {
            "node": NODE_NAME,
            "config": to_dict(self.config),
            "refit_max_visits": self.refit_max_visits,
            "frame_id": self.frame_id,
        }

    def state_dict(self) -> dict[str, Any]:
        """The filter session and the position in the detector's visit stream."""
        return {
            "schema": NODE_STATE_SCHEMA,
            "session": self.session.state_dict(),
            "next_index": self._next_index,
            "end_count": self._end_count,
            "stream": self._stream,
            "first": None if self._first is None else [self._first[0], list(self._first[1])],
            "last_stamp": self._last_stamp,
            "last": None if self.last is None else dataclasses.astuple(self.last),
            "counters": dict(self.counters),
            "retired": [[k, n] for k, n in self._retired.items()],
            "adopt": self._adopt,
        }

    def save_state(self) -> Path:
        """Write :meth:`state_dict` to ``state_file`` (atomically).

        Raises:
            DataError: no ``state_file``, or it cannot be written (the previous file is then unchanged).
        """
        if self.state_file is None:
            msg = "parameter state_file is not set"
            raise DataError(msg)
        self.state_file.parent.mkdir(parents=True, exist_ok=True)
        path = save_filter_state(self.state_file, self.state_dict(), meta=self.state_meta())
        self._unsaved, self.dirty = 0, False
        self.persistence["saves"] += 1
        return path

    def _maybe_autosave(self) -> None:
        if self.autosave_every > 0 and self._unsaved >= self.autosave_every:
            self.autosave()

    def autosave(self) -> None:
        """:meth:`save_state` when a ``state_file`` is set; a failure is logged and counted, not raised."""
        if self.state_file is None:
            return
        try:
            self.save_state()
        except (OSError, DataError) as err:
            self.persistence["save_failures"] += 1
            self._log_once("save-failure", f"cannot save the state to {self.state_file}: {err}")
            return
        self._logger.debug(f"saved the state ({len(self.session.visits)} visits) to {self.state_file}")

    def resume(self, path: Path) -> Reaction:
        """Continue from the state file (if it exists). A file that cannot be used (corrupt, foreign, made
        with another configuration) is moved aside to ``<file>.rejected`` and the filter starts afresh:
        the detector's transient-local history then rebuilds the map."""
        if not path.exists():
            self._logger.info(f"resume: no state file {path} yet; starting afresh")
            return Reaction.NONE
        try:
            state, meta = load_filter_state(path)
            self._check_meta(meta)
            self._load_state(state)
        except (DataError, ConfigError) as err:
            self._reset_all()
            self.persistence["resume_rejected"] += 1
            aside = path.with_name(path.name + ".rejected")
            try:
                path.replace(aside)
            except OSError as move_err:
                aside = Path(f"(not moved: {move_err})")
            self._logger.error(f"cannot resume from {path}: {err}; starting afresh (file kept as {aside})")
            return Reaction.NONE
        n = len(self.session.visits)
        self.persistence["resumed_visits"] = n
        self._logger.info(
            f"resumed from {path}: {n} visits of detector session {self._stream!r}, "
            f"next detector visit {self._next_index}"
        )
        return Reaction.PUBLISH

    def _check_meta(self, meta: dict[str, Any]) -> None:
        mine = self.state_meta()
        offline = meta.get("tool") == RUN_STATE_TOOL  # ptm-run's state: the same session, no stream
        if meta.get("node") != NODE_NAME and not offline:
            writer = meta.get("node") or meta.get("tool")
            msg = f"the state was saved by {writer!r}, not {NODE_NAME} or {RUN_STATE_TOOL}"
            raise DataError(msg)
        for key in ("config",) if offline else ("config", "refit_max_visits"):
            if meta.get(key) != mine[key]:
                diff = differences(meta.get(key), mine[key]) if isinstance(mine[key], dict) else [key]
                msg = f"the state was made with another {key} ({', '.join(diff[:5])} differ)"
                raise ConfigError(msg)

    def _load_state(self, state: dict[str, Any]) -> None:
        if state.get("schema") == SESSION_STATE_SCHEMA:
            self._load_run_state(state)
            return
        if state.get("schema") != NODE_STATE_SCHEMA:
            msg = f"not a {NODE_NAME} state (schema {state.get('schema')!r})"
            raise DataError(msg)
        try:
            self.session.load_state(state["session"])
            self._next_index = None if state["next_index"] is None else int(state["next_index"])
            self._end_count = None if state["end_count"] is None else int(state["end_count"])
            self._stream = state["stream"]
            first = state["first"]
            self._first = None if first is None else (float(first[0]), pose_field(first[1]))
            self._last_stamp = float(state["last_stamp"])
            self.last = None if state["last"] is None else FilterState(*state["last"])
            unknown = set(state["counters"]) - set(COUNTERS)
            if unknown:
                msg = f"unknown counters {sorted(unknown)}"
                raise DataError(msg)
            self.counters.update({k: int(v) for k, v in state["counters"].items()})
            self._retired = {str(k): int(n) for k, n in state["retired"]}
            self._adopt = int(state.get("adopt", 0))  # absent in states saved before ptm-run's were read
        except (KeyError, TypeError, ValueError, IndexError) as err:
            msg = f"malformed {NODE_NAME} state: {type(err).__name__}: {err}"
            raise DataError(msg) from err
        self._resumed = dict(self._retired.items())
        self._resumed[self._stream] = self._next_index or 0
        self._unsaved, self.dirty = 0, False

    def _load_run_state(self, state: dict[str, Any]) -> None:
        """Continue from ``ptm-run``'s state (its session's, :data:`~ptm_ros.session.SESSION_STATE_SCHEMA`):
        the map holds its visits; the first detector session that delivers one of them (same index,
        stamp and pose) is adopted, its visits up to there redelivered, the later ones filtered."""
        self.session.load_state(state)
        visits = self.session.visits
        n = len(visits)
        self._next_index = n if n else None
        self._stream, self._end_count, self._adopt = None, None, n
        self._first = (visits[0].stamp, visits[0].pose) if n else None
        self._last_stamp = visits[-1].stamp if n else -math.inf
        self._retired, self._resumed = {}, {}
        self._unsaved, self.dirty = 0, False

    def _reset_all(self) -> None:
        self.session.reset()
        self._next_index = self._end_count = self._stream = self._first = self.last = None
        self._last_stamp = -math.inf
        self.counters.update(dict.fromkeys(COUNTERS, 0))
        self._retired, self._resumed, self._adopt = {}, {}, 0


def visit_line(index: int, state: FilterState, map_mass: float, *, how: str, ms: float) -> str:
    """The log line after a visit: the effective sample size ``1/Σw²`` as a share of the particles it is
    computed over (each particle a distinct topology, so it is near 1 whenever one topology holds nearly
    all the mass: the line says how much), and the update's time.

    ``visit_line(7, state, 0.806, how="updated", ms=56.3)`` →
    ``"visit 7: ESS 1.46/100 particles (each a distinct topology; the most probable holds 0.806),
    updated in 56 ms"``.
    """
    return (
        f"visit {index}: ESS {ess_fraction(state.ess, state.n_topologies)} particles (each a distinct "
        f"topology; the most probable holds {map_mass:.3f}), {how} in {ms:.0f} ms"
    )
