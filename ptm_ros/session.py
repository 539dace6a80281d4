"""The mapping session: a configuration and a stream of landmark visits in, a PTM out (the orchestration).

``ptm-run`` (:mod:`ptm_ros.tools.pipeline`) and the ``topology_filter`` node are two thin drivers of the
code here, as kiss-icp's ``OdometryPipeline`` and its ROS wrapper drive one ``KissICP``:

* :class:`FilterSession` — the Rao-Blackwellized particle filter over topologies (thesis Algorithm 8,
  :mod:`ptm_ros.inference.rbpf`) fed one visit at a time, with its laser registrations cached per pair and one
  checkpoint schema (:data:`SESSION_STATE_SCHEMA`) that both drivers save and resume;
* :func:`infer` — the batch estimators over a whole visit sequence: exact enumeration (Ch. 2.1), MCMC /
  MC³ (Ch. 3.1–3.6, started from the filter's topologies on long runs) and the filter itself;
* :func:`build_ptm` — the ptm.json content (CONTRACT.md schema) of an :class:`Inference`.

Appearance priors. The appearance model's priors are fitted to the visits by empirical Bayes
(:func:`ptm_ros.model.appearance.fit_appearance_model`). Offline the whole run is known, and the priors are
fitted once to all of its visits (``fitted_to``), as the batch posterior is. A live stream only knows the
visits so far: the session re-fits the priors after every visit and, when they change, replays the
(deterministic, seeded) filter over the visits so far, so that after every visit the ensemble is exactly
the offline one on those visits. Beyond ``refit_max_visits`` visits the priors are frozen as fitted then
and the filter only moves forward (a replay costs one filter update per visit so far).

Heading noise. With ``model.odometry.learn_heading``, the scale of the odometry's heading noise is learned
from the laser registrations the filter has made (:mod:`ptm_ros.model.heading_noise`). After every visit the
session re-estimates it and, when the estimate has moved :data:`HEADING_HYSTERESIS` lattice steps from the
scale in use, replays the filter over the visits so far with the new one (the registrations are cached,
so a replay registers only pairs it has not seen). The rule depends on the visits alone, so a stream
learns the same scale at the same visits as an offline run, and ends with the same ensemble; a live
stream freezes the scale with the priors beyond ``refit_max_visits`` visits, an offline run never (as
``ptm-bringup``'s stream, ``refit_max_visits`` 0).

Visit offset. With ``model.odometry.learn_offset``, the spread ``sigma_offset`` of where along its heading
the detector puts a visit is learned the same way (:mod:`ptm_ros.model.visit_offset`, lattice steps of
0.125 m, a replay when the estimate has moved :data:`OFFSET_HYSTERESIS` steps).

Checkpoints. :meth:`FilterSession.state_dict` holds the visits with their measurements, the registration
cache and its counters, the appearance priors in use, and the particle filter's own
:meth:`~ptm_ros.inference.rbpf.TopologyFilter.state_dict`. A session restored from it continues exactly where
it stopped. A session whose priors are fitted to the whole run (``fitted_to``) that restores a state made
with other priors (a live node's) replays the restored visits with its own priors: the result is then
exactly that of an uninterrupted offline run.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ptm_ros.config import PtmConfig
from ptm_ros.errors import ConfigError, DataError, ModelError, PtmError
from ptm_ros.factories import Registration, cached, make_registrar
from ptm_ros.inference.persistence import (
    appearance_from_state,
    appearance_to_state,
    registrations_from_state,
    registrations_to_state,
    visit_from_state,
    visit_to_state,
)
from ptm_ros.inference.rbpf import FilterState, Prefetch, RbpfConfig, TopologyFilter
from ptm_ros.model.appearance import AppearanceModel
from ptm_ros.model.geometry import Registrar, RelativePose
from ptm_ros.model.heading_noise import (
    NoiseScale,
    heading_residuals,
    heading_scale,
    profiled_outlier,
    scaled_heading_noise,
)
from ptm_ros.model.odometry import OdometryConfig
from ptm_ros.model.partitions import Labels
from ptm_ros.model.posterior import (
    PosteriorModel,
    exact_posterior,
    normalize_log,
    same_place_probabilities,
    top_k,
    total_variation,
)
from ptm_ros.model.priors import make_prior
from ptm_ros.model.ptm import (
    GREEDY_KEY,
    TIMELINE_KEY,
    Landmark,
    Ptm,
    TimelineStep,
    greedy_dict,
    make_ptm,
    timeline_list,
)
from ptm_ros.model.translation_noise import TRANSLATION_KEY, translation_residuals, translation_scale
from ptm_ros.model.visit_offset import OffsetSpread, offset_spread
from ptm_ros.model.visits import Visit
from ptm_ros.perception.laser import PatchRegistrar, WorkerPool
from ptm_ros.reporting.doubts import doubts_dict, find_doubts
from ptm_ros.scoring.baselines import GreedyAssociation, GreedyConfig, greedy_association

#: A progress wrapper: ``progress(items, total)`` yields the items (e.g. a tqdm bar); None: none.
Progress = Callable[[Iterable[Any], int], Iterable[Any]]
#: Schema tag of :meth:`FilterSession.state_dict` (``ptm-run``'s state file and inside the node's).
SESSION_STATE_SCHEMA = "ptm_ros.filter_session/2"
#: ``meta["tool"]`` of ``ptm-run``'s state files (the ``topology_filter`` node resumes them too).
RUN_STATE_TOOL = "ptm-run"
#: ``ptm.inference`` key of MCMC's comparison with the particle filter it started from.
VERSUS_KEY = "versus_rbpf"
#: ``ptm.extra`` key of the visits the map is unsure of (:func:`ptm_ros.reporting.doubts.doubts_dict`).
DOUBTS_KEY = "doubts"
#: ``ptm.inference`` key of the learned heading-noise scale
# (:class:`ptm_ros.model.heading_noise.NoiseScale`).
HEADING_KEY = "heading_noise"
#: ``ptm.inference`` key of the learned visit offset (:class:`ptm_ros.model.visit_offset.OffsetSpread`).
OFFSET_KEY = "visit_offset"
#: The learned visit offset moves (and the filter replays) only when the estimate is this many lattice steps
#: (:data:`ptm_ros.model.visit_offset.STEP_M`) from the value in use.
OFFSET_HYSTERESIS = 2
#: The learned heading-noise scale moves (and the filter replays) only when the estimate is this many
#: lattice steps (factors √2) away from the one in use, so that it does not flip between neighbours.
HEADING_HYSTERESIS = 2
#: The heading-noise scale before anything is learned: the model as configured.
UNLEARNED = NoiseScale(1.0, 0, 0.0, 0)


@dataclass(frozen=True)
class Inference:
    """A PTM's topologies with probabilities, and method-specific details; ``greedy`` the single answer
    of the greedy baseline on the same visits (:func:`ptm_ros.scoring.baselines.greedy_association`), if
    known."""

    probabilities: dict[Labels, float]
    positions: dict[Labels, np.ndarray]
    log_posteriors: dict[Labels, float]
    details: dict[str, Any]
    greedy: Labels | None = None


def require_rbpf(config: PtmConfig, what: str) -> None:
    """Refuse another inference method than the particle filter for ``what`` (a streaming use).

    Raises:
        ConfigError: ``inference.method`` is not ``rbpf``.
    """
    method = config.inference.method
    if method != "rbpf":
        msg = (
            f"{what} needs the particle filter (inference.method: rbpf), got {method!r}; "
            f"use ptm-run for '{method}'"
        )
        raise ConfigError(msg)


def same_model(a: Any, b: Any) -> bool:
    """Whether two fitted appearance models (or None) are identical, array by array."""
    if a is None or b is None:
        return a is b
    if dataclasses.is_dataclass(a):
        return type(a) is type(b) and all(
            same_model(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(a)
        )
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return bool(np.array_equal(a, b))
    return bool(a == b)


# -------------------------------------------------------------------------------------- filter session


class FilterSession:
    """The RBPF over a stream of visits: after every visit, the offline RBPF on the visits so far.

    Args:
        config: the configuration (``inference.method`` must be ``rbpf``).
        refit_max_visits: re-fit the appearance priors (and replay when they change) up to this many
            visits; later the priors stay as fitted then. 0: always.
        fitted_to: the whole run's visits when they are known in advance (offline): the priors are
            fitted to them once and never re-fitted (the visits added must be a prefix of them).
        registrar: a laser registrar over the run's visits to share with other users (offline: the batch
            model of MCMC); default: one over the session's own visits, counting into
            :attr:`registrations`. Either way the session caches its outcomes per pair.
        workers: where the session's own registrar registers the pairs a visit needs, in parallel
            (:meth:`ptm_ros.perception.laser.PatchRegistrar.many`; the same outcomes); default: one by one,
            here.

    With ``inference.greedy``, beside the filter the session runs the greedy baseline
    (:class:`ptm_ros.scoring.baselines.GreedyAssociation`, odometry only, decisions final) on the same visits,
    one decision per visit; a restored session
    decides the restored visits again (the same answer: it depends on the visits alone).

    Raises:
        ConfigError: another inference method, or ``refit_max_visits < 0``.
    """

    def __init__(
        self,
        config: PtmConfig,
        *,
        refit_max_visits: int = 100,
        fitted_to: Sequence[Visit] | None = None,
        registrar: Registrar | None = None,
        workers: WorkerPool | None = None,
    ) -> None:
        require_rbpf(config, "a filter session")
        if refit_max_visits < 0:
            msg = f"refit_max_visits must be >= 0, got {refit_max_visits}"
            raise ConfigError(msg)
        self.config = config
        self.refit_max_visits = refit_max_visits
        self.registrations: dict[str, Any] = {}  # the registrar's counters
        self._visits: list[Visit] = []
        self._pairs: dict[tuple[int, int], Registration] = {}
        self._filter: TopologyFilter | None = None
        self._fitted: AppearanceModel | None = None
        self._run: tuple[Visit, ...] | None = None if fitted_to is None else tuple(fitted_to)
        if self._run:
            self._fitted = self._fit(self._run)
        self._built_at = 0  # visits when the filter was last (re)built
        self.replays = 0
        self.wall_s = 0.0
        self._heading = UNLEARNED
        self._offset = OffsetSpread.prior(config.model.odometry.sigma_offset)
        inner = registrar
        own = None
        if inner is None and config.model.use_laser:
            inner = own = make_registrar(self._visits, config, self.registrations)
        self._registrar = None if inner is None or not config.model.use_laser else cached(inner, self._pairs)
        self._prefetch: Prefetch | None = None
        if own is not None and workers is not None:
            self._prefetch = functools.partial(_register_many, own, workers, self._pairs)
        self._greedy: GreedyAssociation | None = None
        self._start_greedy()

    def _fit(self, visits: Sequence[Visit]) -> AppearanceModel | None:
        """The appearance priors fitted to ``visits`` (the same model object ``PosteriorModel`` builds)."""
        return PosteriorModel(visits, self.config.model, seed=self.config.inference.seed).appearance

    @property
    def visits(self) -> tuple[Visit, ...]:
        """The visits processed so far."""
        return tuple(self._visits)

    @property
    def filter(self) -> TopologyFilter | None:
        """The particle filter (None before the first visit)."""
        return self._filter

    @property
    def registrar(self) -> Registrar | None:
        """The cached laser registrar over the session's visits (None without laser)."""
        return self._registrar

    @property
    def pairs(self) -> Mapping[tuple[int, int], Registration]:
        """The registrations made so far, per visit pair ``(i, j)``."""
        return self._pairs

    @property
    def greedy(self) -> Labels | None:
        """The greedy baseline's labels of the visits so far (None: its pose graph could not be solved
        at some visit, and it stopped)."""
        return None if self._greedy is None else self._greedy.labels

    def _start_greedy(self) -> None:
        """A fresh greedy baseline when ``inference.greedy`` asks for one."""
        on = self.config.inference.greedy
        self._greedy = GreedyAssociation(self.config.model.odometry, GreedyConfig()) if on else None

    def _decide_greedy(self, visits: Sequence[Visit]) -> None:
        """The greedy baseline's decision on the last of ``visits`` (the ones it decided, then one more);
        a failure stops the baseline, not the map."""
        if self._greedy is None:
            return
        try:
            self._greedy.add(visits)
        except ModelError:
            self._greedy = None

    def add(self, visit: Visit) -> FilterState:
        """Process the next visit (``visit.index`` must equal the number of visits so far).

        Raises:
            DataError: a visit out of order.
            ModelError: a visit the models cannot use; the session is unchanged.
        """
        start = time.perf_counter()
        n = len(self._visits)
        if visit.index != n:
            msg = f"expected visit {n}, got visit {visit.index}"
            raise DataError(msg)
        if self._run is not None and (n >= len(self._run) or self._run[n] != visit):
            msg = f"visit {n} is not the run's visit {n} that the appearance priors were fitted to"
            raise DataError(msg)
        self._visits.append(visit)
        try:
            state = self._advance(visit)
        except BaseException:
            self._visits.pop()
            for key in [k for k in self._pairs if k[1] == n]:
                del self._pairs[key]
            raise
        self._decide_greedy(self._visits)
        self.wall_s += time.perf_counter() - start
        return state

    def _advance(self, visit: Visit) -> FilterState:
        return self._learn_offset(self._learn_heading(self._advance_appearance(visit)))

    def _frozen(self) -> bool:
        """Whether the learned parts (appearance priors, heading noise) are frozen: beyond
        ``refit_max_visits`` visits."""
        return 0 < self.refit_max_visits < len(self._visits)

    def _advance_appearance(self, visit: Visit) -> FilterState:
        old = self._filter
        if self._run is not None:
            if old is not None:
                return old.update(visit)
            return self._rebuild(self._fitted)
        appearance = self._fit(self._visits)
        if old is not None and self._keeps(old.appearance, appearance):
            return old.update(visit)
        return self._rebuild(appearance)

    def _keeps(self, old: AppearanceModel | None, new: AppearanceModel | None) -> bool:
        """Whether the filter keeps its appearance priors ``old`` when the visits so far fit ``new``: they
        are the same, or the priors are frozen and appearance is neither switched on nor off."""
        return same_model(new, old) or (self._frozen() and (new is None) == (old is None))

    def _learning_frozen(self) -> bool:
        """Whether the learned noise parameters stay as they are: a live stream beyond ``refit_max_visits``
        (offline, as a never-frozen stream: ``ptm-bringup``)."""
        return self._run is None and self._frozen()

    def _valid_registrations(self) -> list[RelativePose]:
        """The valid registrations so far, what the heading noise and the visit offset are learned from."""
        return [z for z in self._pairs.values() if isinstance(z, RelativePose)]

    def _to_learn_from(self, enabled: bool, seen: int) -> list[RelativePose] | None:
        """The valid registrations so far when a learned parameter is to be estimated again: its learning
        ``enabled``, a filter to replay, not frozen, and other registrations than the ``seen`` it was last
        estimated from; else None."""
        if not enabled or self._filter is None or self._learning_frozen():
            return None
        valid = self._valid_registrations()
        return None if len(valid) == seen else valid

    def _learn_heading(self, state: FilterState) -> FilterState:
        """Re-estimate the heading-noise scale from the registrations so far (module docstring) and replay
        the filter with it when it moved by :data:`HEADING_HYSTERESIS` steps or more."""
        cfg = self.config.model.odometry
        valid = self._to_learn_from(cfg.learn_heading, self._heading.registrations)
        if valid is None or self._filter is None:
            return state
        residuals = heading_residuals(self._visits, valid, cfg)
        learned = heading_scale(residuals, cfg.heading_prior_sd)
        if abs(learned.step - self._heading.step) < HEADING_HYSTERESIS:  # the scale stays; its report moves
            outliers = profiled_outlier(residuals, self._heading.step)
            self._heading = replace(self._heading, registrations=len(residuals), outlier_fraction=outliers)
            return state
        self._heading = learned
        return self._rebuild(self._filter.appearance)

    def _learn_offset(self, state: FilterState) -> FilterState:
        """Re-estimate the visit offset's spread from the registrations so far (module docstring) and replay
        the filter with it when it moved by :data:`OFFSET_HYSTERESIS` steps or more."""
        cfg = self.config.model.odometry
        valid = self._to_learn_from(cfg.learn_offset, self._offset.registrations)
        if valid is None or self._filter is None:
            return state
        learned = offset_spread(valid, cfg.sigma_offset)
        if abs(learned.step - self._offset.step) < OFFSET_HYSTERESIS:  # the value stays; its report moves
            self._offset = replace(self._offset, samples=learned.samples, registrations=learned.registrations)
            return state
        self._offset = learned
        return self._rebuild(self._filter.appearance)

    @property
    def offset(self) -> OffsetSpread:
        """The visit offset's spread in use (the configured value until one is learned)."""
        return self._offset

    @property
    def heading(self) -> NoiseScale:
        """The heading-noise scale in use (:data:`UNLEARNED` until one is learned)."""
        return self._heading

    def odometry_config(self) -> OdometryConfig:
        """The odometry model in use: the configured one with the learned heading-noise scale and visit
        offset."""
        odometry = scaled_heading_noise(self.config.model.odometry, self._heading.scale)
        return replace(odometry, sigma_offset=self._offset.sigma) if odometry.learn_offset else odometry

    def _new_filter(self, appearance: AppearanceModel | None) -> TopologyFilter:
        inf = self.config.inference
        return TopologyFilter(
            rbpf_config(self.config),
            make_prior(self.config.model.prior),
            self.odometry_config(),
            appearance=appearance,
            registrar=self._registrar,
            seed=inf.seed,
            prefetch=self._prefetch,
        )

    def _rebuild(self, appearance: AppearanceModel | None) -> FilterState:
        """A new filter with ``appearance`` priors, run over every visit so far (a replay when one
        existed)."""
        new = self._new_filter(appearance)
        state = None
        for v in self._visits:
            state = new.update(v)
        if state is None:
            msg = "a filter session rebuilds only over at least one visit"
            raise DataError(msg)
        self.replays += int(self._filter is not None)
        self._filter = new
        self._built_at = len(self._visits)
        return state

    def reset(self) -> None:
        """Forget every visit (priors fitted to a known run, ``fitted_to``, are kept)."""
        self._visits.clear()
        self._pairs.clear()
        self._filter = None
        self._built_at = 0
        self.replays = 0
        self.wall_s = 0.0
        self._heading = UNLEARNED
        self._offset = OffsetSpread.prior(self.config.model.odometry.sigma_offset)
        self.registrations.clear()
        self._start_greedy()

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to continue the session (plain values and arrays, for
        :func:`ptm_ros.inference.persistence.save_filter_state`); schema :data:`SESSION_STATE_SCHEMA`."""
        flt = self._filter
        return {
            "schema": SESSION_STATE_SCHEMA,
            "visits": [visit_to_state(v) for v in self._visits],
            "pairs": registrations_to_state(self._pairs),
            "registrations": dict(self.registrations),
            "appearance": None if flt is None else appearance_to_state(flt.appearance),
            "built_at": self._built_at,
            "replays": self.replays,
            "wall_s": self.wall_s,
            "heading": self._heading.as_dict(),
            "offset": self._offset.as_dict(),
            "filter": None if flt is None else flt.state_dict(),
        }

    def load_state(self, state: Mapping[str, Any]) -> None:
        """Replace the session by a saved one (:meth:`state_dict`), continuing exactly where it stopped:
        with the saved appearance priors, or (``fitted_to``) with this session's, replaying the saved
        visits when they differ.

        Raises:
            DataError: a state of another schema or a malformed one (the session is then empty).
        """
        if not isinstance(state, Mapping) or state.get("schema") != SESSION_STATE_SCHEMA:
            schema = state.get("schema") if isinstance(state, Mapping) else type(state).__name__
            msg = f"not a filter session state ({SESSION_STATE_SCHEMA}), got schema {schema!r}"
            raise DataError(msg)
        self.reset()
        try:
            self._visits.extend(visit_from_state(d) for d in state["visits"])  # the registrar's list
            self._pairs.update(registrations_from_state(state["pairs"]))
            self.registrations.update(state["registrations"])
            self._built_at = int(state["built_at"])
            self.replays = int(state["replays"])
            self.wall_s = float(state["wall_s"])
            heading = state.get("heading")  # absent in states saved before it was learned
            self._heading = UNLEARNED if heading is None else NoiseScale.from_dict(heading)
            offset = state.get("offset")  # absent in states saved before it was learned
            if offset is not None:
                self._offset = OffsetSpread.from_dict(offset)
            if state["filter"] is not None:
                self._filter = self._restore_filter(
                    state["filter"], appearance_from_state(state["appearance"])
                )
            for k in range(len(self._visits)):  # the greedy baseline's decisions, made again
                self._decide_greedy(self._visits[: k + 1])
        except (KeyError, IndexError, TypeError, ValueError, PtmError) as err:
            self.reset()
            msg = f"malformed filter session state: {type(err).__name__}: {err}"
            raise DataError(msg) from err

    def _restore_filter(self, state: dict[str, Any], appearance: AppearanceModel | None) -> TopologyFilter:
        if [v.index for v in self._visits] != list(range(len(self._visits))):
            msg = "the saved visits are not numbered 0, 1, 2, ..."
            raise DataError(msg)
        if not 1 <= self._built_at <= len(self._visits):
            msg = f"the filter was built on {self._built_at} of {len(self._visits)} visits"
            raise DataError(msg)
        flt = TopologyFilter.from_state_dict(
            state,
            rbpf_config(self.config),
            make_prior(self.config.model.prior),
            self.odometry_config(),
            appearance=appearance,
            registrar=self._registrar,
            prefetch=self._prefetch,
        )
        if flt.visits != tuple(self._visits):
            msg = "the filter's visits differ from the session's"
            raise DataError(msg)
        if self._run is not None and self._run[: len(self._visits)] != flt.visits:
            msg = "the saved visits are not the first ones of the run the priors were fitted to"
            raise DataError(msg)
        if self._run is not None and not same_model(appearance, self._fitted):
            self._filter = flt
            self._rebuild(self._fitted)  # another session's priors: replay with this run's
            return self._filter
        return flt

    def inference(self) -> Inference:
        """The current ensemble as an :class:`Inference` (the ``inference.top`` most probable).

        Raises:
            DataError: no visit yet.
        """
        flt = self._filter
        if flt is None:
            msg = "no visit has been processed yet"
            raise DataError(msg)
        return rbpf_inference(
            flt,
            self.config,
            greedy=self.greedy,
            **({HEADING_KEY: self._heading.as_dict()} if self.config.model.odometry.learn_heading else {}),
            **({OFFSET_KEY: self._offset.as_dict()} if self.config.model.odometry.learn_offset else {}),
            **({} if self._registrar is None else {TRANSLATION_KEY: self.translation_noise().as_dict()}),
            **({} if self._run is not None else {"replays": self.replays}),
        )

    def translation_noise(self) -> NoiseScale:
        """The translation-noise scale the valid registrations so far suggest at the heading scale in use
        (:func:`ptm_ros.model.translation_noise.translation_scale`): a check of the odometry model, not
        used by the filter."""
        valid = self._valid_registrations()
        cfg = self.config.model.odometry
        return translation_scale(translation_residuals(self._visits, valid, cfg), self._heading.scale, cfg)

    def to_ptm(self, *, frame_id: str = "odom", **extra: Any) -> Ptm:
        """The current PTM (as :func:`build_ptm` writes it)."""
        return build_ptm(
            self._visits, self.inference(), self.config, frame_id=frame_id, wall_s=self.wall_s, **extra
        )


def _register_many(
    registrar: PatchRegistrar,
    workers: WorkerPool,
    cache: dict[tuple[int, int], Registration],
    pairs: list[tuple[int, int]],
) -> None:
    """Register the ``pairs`` not in ``cache`` with ``workers`` and cache them (a session's prefetch)."""
    todo = [p for p in pairs if p not in cache]
    if len(todo) > 1:  # one pair is as fast here
        cache.update(registrar.many(todo, workers))


def filter_visits(
    session: FilterSession,
    visits: Sequence[Visit],
    *,
    progress: Progress | None = None,
    save: Callable[[FilterSession], None] | None = None,
    every: int = 1,
) -> FilterSession:
    """Feed a session the visits of ``visits`` it has not seen yet (a resumed session continues), calling
    ``save`` after every ``every``-th visit and after the last one (when it was not just saved)."""
    done = len(session.visits)
    todo = visits[done:]
    items: Iterable[Visit] = todo if progress is None or not todo else progress(todo, len(todo))
    saved_at = done if done else -1
    for visit in items:
        session.add(visit)
        if save is not None and len(session.visits) % every == 0:
            save(session)
            saved_at = len(session.visits)
    if save is not None and session.visits and saved_at != len(session.visits):
        save(session)
    return session


def rbpf_config(config: PtmConfig) -> RbpfConfig:
    """The particle filter's settings: ``inference.particles`` and ``resample``, and ``inference.timeline``
    topologies recorded after each visit."""
    inf = config.inference
    return RbpfConfig(
        particles=inf.particles,
        particles_max=inf.particles_max,
        thinned_mass=inf.thinned_mass,
        resample=inf.resample,
        record_top=inf.timeline,
        reweight=inf.reweight,
    )


def filter_timeline(history: Sequence[FilterState]) -> tuple[TimelineStep, ...]:
    """The PTM after each visit, as the filter recorded it (:attr:`ptm_ros.inference.rbpf.FilterState.top`,
    by its sequential weights): the posterior of thesis Algorithm 8 over the topologies of the visits so
    far; empty when none recorded. (:func:`rbpf_inference` replaces the last step by the PTM's own top,
    which the batch evidence may have reweighted.)"""
    if not any(h.top for h in history):
        return ()
    return tuple(TimelineStep(h.n_visits, h.top) for h in history)


def rbpf_inference(
    flt: TopologyFilter, config: PtmConfig, *, greedy: Labels | None = None, **details: Any
) -> Inference:
    """A particle filter's current ensemble as an :class:`Inference`, with its timeline
    (:func:`filter_timeline`, under :data:`~ptm_ros.model.ptm.TIMELINE_KEY` when recorded) and ``greedy``."""
    inf = config.inference
    probs = flt.ptm_weights()
    logw = flt.log_weights()
    rw = flt.reweighted()
    ranked = dict(top_k(probs, inf.top))
    updates = np.array([h.update_s for h in flt.history])
    timeline = filter_timeline(flt.history)
    if timeline and rw is not None:  # the last step is the PTM itself, reweighted
        timeline = (*timeline[:-1], TimelineStep(timeline[-1].visits, tuple(top_k(probs, inf.timeline))))
    return Inference(
        probabilities=ranked,
        positions={lab: flt.place_positions(lab) for lab in ranked},
        log_posteriors={lab: logw[lab] for lab in ranked},
        details={
            "resample": inf.resample,
            "n_topologies": flt.n_topologies,
            **(
                {"particles_peak": max((h.n_topologies for h in flt.history), default=0)}
                if inf.particles_cap > inf.particles
                else {}
            ),
            "ess": flt.history[-1].ess if flt.history else 0.0,
            "log_evidence": flt.log_evidence,
            "update_ms_median": float(np.median(updates) * 1e3) if len(updates) else 0.0,
            "update_ms_p95": float(np.percentile(updates, 95) * 1e3) if len(updates) else 0.0,
            "reweighted": rw is not None,
            **({"reweight_failure": flt.reweight_failure} if flt.reweight_failure is not None else {}),
            "reweight_ms": rw.seconds * 1e3 if rw is not None else 0.0,
            **({TIMELINE_KEY: timeline_list(timeline)} if timeline else {}),
            **details,
        },
        greedy=greedy,
    )


def build_ptm(
    visits: Sequence[Visit],
    inference: Inference,
    config: PtmConfig,
    *,
    frame_id: str,
    wall_s: float,
    **extra: Any,
) -> Ptm:
    """The ptm.json content of an inference result, with the visits the map is unsure of
    (``extra["doubts"]``, :func:`ptm_ros.reporting.doubts.find_doubts`) and the greedy baseline's answer
    (``extra["greedy"]``, :func:`ptm_ros.model.ptm.greedy_dict`) when the inference has one."""
    landmarks = [Landmark.from_visit(v) for v in visits]
    inf = config.inference
    if inference.greedy is not None:
        extra = {**extra, GREEDY_KEY: greedy_dict(inference.greedy, GreedyConfig().gate_probability)}
    ptm = make_ptm(
        landmarks,
        inference.probabilities,
        positions=inference.positions,
        log_posteriors=inference.log_posteriors,
        frame_id=frame_id,
        inference={"method": inf.method, "particles": inf.particles, "seed": inf.seed, **inference.details},
        timing={"wall_s": wall_s},
        extra=extra,
    )
    return replace(ptm, extra={**ptm.extra, DOUBTS_KEY: doubts_dict(find_doubts(ptm))})


# ------------------------------------------------------------------------------------ batch estimators


def infer(
    visits: Sequence[Visit],
    config: PtmConfig,
    *,
    session: FilterSession | None = None,
    registrar: Registrar | None = None,
    progress: Progress | None = None,
    sweeps: Callable[[int, int], None] | None = None,
) -> Inference:
    """Run the configured estimator over a visit sequence.

    ``rbpf`` feeds ``session`` (a fresh one fitted to ``visits`` when None, registering with
    ``registrar`` or, without one and with ``model.use_laser``, its own; a restored one continues) the
    visits it has not seen; ``exact`` and ``mcmc`` score topologies with the batch model, laser pairs
    from ``registrar`` (none without one). ``progress`` wraps the filter's visits and the enumeration's
    topologies; ``sweeps`` hears of MCMC's sweeps (:func:`ptm_ros.inference.mcmc.run_mcmc`'s ``progress``).

    Raises:
        DataError: no visits.
        ConfigError: an unknown method, or exact enumeration over more than ``max_exact_visits``.
    """
    inf = config.inference
    if not visits:
        msg = "no landmark visits were detected: nothing to infer"
        raise DataError(msg)
    if inf.method == "rbpf":
        if session is None:
            session = FilterSession(config, fitted_to=visits, registrar=registrar)
        return filter_visits(session, visits, progress=progress).inference()
    return replace(
        _infer_batch(visits, config, registrar, progress, sweeps), greedy=_greedy_of(visits, config)
    )


def _greedy_of(visits: Sequence[Visit], config: PtmConfig) -> Labels | None:
    """The greedy baseline's answer on a whole run (None: not asked for by ``inference.greedy``, or its
    pose graph could not be solved)."""
    if not config.inference.greedy:
        return None
    try:
        return greedy_association(visits, config.model.odometry, GreedyConfig())
    except ModelError:
        return None


def _infer_batch(
    visits: Sequence[Visit],
    config: PtmConfig,
    registrar: Registrar | None,
    progress: Progress | None,
    sweeps: Callable[[int, int], None] | None,
) -> Inference:
    """:func:`infer` for the batch estimators, ``exact`` and ``mcmc``: the batch model with the heading
    noise and visit offset the particle filter learns on the same visits (:func:`_filter_pass`, when MCMC
    starts from the filter's ensemble or ``model.odometry.learn_heading`` / ``learn_offset`` is on)."""
    from ptm_ros.inference.mcmc import starts_from_filter

    inf = config.inference
    if inf.method == "exact" and len(visits) > inf.max_exact_visits:
        msg = (
            f"exact enumeration over {len(visits)} visits is too large: inference.max_exact_visits is "
            f"{inf.max_exact_visits} (at most 12); use --method rbpf or --method mcmc"
        )
        raise ConfigError(msg)
    starts = inf.method == "mcmc" and starts_from_filter(inf.mcmc, len(visits))
    odometry = config.model.odometry
    learning = odometry.learn_heading or odometry.learn_offset
    learn = learning and registrar is not None and config.model.use_laser
    session = _filter_pass(visits, config, registrar, progress) if starts or learn else None
    model_config = config.model
    heading: dict[str, Any] = {}
    if session is not None and learn:
        model_config = replace(config.model, odometry=session.odometry_config())
        heading = {
            **({HEADING_KEY: session.heading.as_dict()} if odometry.learn_heading else {}),
            **({OFFSET_KEY: session.offset.as_dict()} if odometry.learn_offset else {}),
            TRANSLATION_KEY: session.translation_noise().as_dict(),
        }
    model = PosteriorModel(visits, model_config, registrar=registrar, seed=inf.seed)
    if inf.method == "exact":
        logp = exact_posterior(model, progress=progress)
        probs = normalize_log(logp)
        ranked = dict(top_k(probs, inf.top))
        return Inference(
            probabilities=ranked,
            positions=_metric_positions(model, ranked),
            log_posteriors={lab: logp[lab] for lab in ranked},
            details={"n_topologies_evaluated": len(logp), **heading},
        )
    if inf.method == "mcmc":
        # the filter's ensemble: the starts and the yardstick
        ensemble = session.inference().probabilities if starts and session is not None else None
        out = _infer_mcmc(model, config, ensemble, sweeps)
        return replace(out, details={**out.details, **heading})
    msg = f"inference method {inf.method!r} is not available"
    raise ConfigError(msg)


def _filter_pass(
    visits: Sequence[Visit], config: PtmConfig, registrar: Registrar | None, progress: Progress | None
) -> FilterSession:
    """The particle filter over ``visits`` beside a batch estimator, on the same data (laser pairs from
    ``registrar``, none without one), listing all its particles: MCMC's starts and yardstick, and the
    heading noise it learns."""
    every = replace(
        config,
        model=replace(config.model, use_laser=registrar is not None and config.model.use_laser),
        inference=replace(config.inference, method="rbpf", top=config.inference.particles_cap),
    )
    session = FilterSession(every, fitted_to=visits, registrar=registrar)
    return filter_visits(session, visits, progress=progress)


def _metric_positions(model: PosteriorModel, labels: Iterable[Labels]) -> dict[Labels, np.ndarray]:
    """Optimised place positions of some topologies (from the cached metric likelihood)."""
    out = {}
    for lab in labels:
        res = model.terms(lab).metric_result
        if res is not None:
            out[lab] = res.place_positions
    return out


def _infer_mcmc(
    model: PosteriorModel,
    config: PtmConfig,
    ensemble: Mapping[Labels, float] | None = None,
    sweeps: Callable[[int, int], None] | None = None,
) -> Inference:
    """Batch MCMC over set partitions (thesis Ch. 2.1, 3.1-3.6), stopping when converged; with the
    particle filter's ``ensemble`` (``initial: rbpf``, or ``auto`` on a long run), chain c starts from
    its c-th topology and the details compare the two PTMs (:func:`compare_to_filter`)."""
    from ptm_ros.inference.mcmc import initial_kind, run_mcmc

    inf = config.inference
    starts = None if ensemble is None else list(ensemble)[: inf.mcmc.chains]
    res = run_mcmc(model, inf.mcmc, inf.seed, initial=starts, progress=sweeps)
    ranked = dict(top_k(res.probabilities, inf.top))
    d = res.diagnostics
    versus = {} if ensemble is None else {VERSUS_KEY: compare_to_filter(model, res.probabilities, ensemble)}
    return Inference(
        probabilities=ranked,
        positions=_metric_positions(model, ranked),
        log_posteriors={lab: res.log_posteriors[lab] for lab in ranked},
        details={
            "estimate": inf.mcmc.estimate,
            "iterations": d.iterations,
            "chains": d.chains,
            "betas": list(d.betas),
            "converged": d.converged,
            "stop_reason": d.stop_reason,
            "doubling_tv": d.doubling_tv,
            "chain_tv": d.chain_tv,
            "doubling_pair": d.doubling_pair,
            "chain_pair": d.chain_pair,
            "n_evaluated": d.n_evaluated,
            "samples": res.samples,
            "acceptance": dict(d.acceptance),
            "initial": initial_kind(inf.mcmc, model.n),
            **versus,
            **cold_chain_details(res),
        },
    )


def compare_to_filter(
    model: PosteriorModel, mcmc: Mapping[Labels, float], rbpf: Mapping[Labels, float]
) -> dict[str, Any]:
    """How an MCMC PTM differs from a particle filter's (issue #7): total variation to the filter's PTM
    and to its topologies re-weighted by the batch posterior (so only the support differs), the log
    posterior of each MAP under the batch model (``map_gain_nats`` > 0: MCMC found a topology the filter
    ranked lower or lost), and the same-place marginals of the visit pairs either PTM gives >= 0.01
    (:func:`same_place_probabilities`): largest and mean absolute difference, and how many differ by more
    than 0.1. With many near-equal topologies (long runs) two samplers can share little of their support
    (TV near 1) yet agree on which visits are one place."""
    mcmc_map = max(mcmc, key=mcmc.__getitem__)
    rbpf_map = max(rbpf, key=rbpf.__getitem__)
    reweighted = normalize_log({lab: model.log_posterior(lab) for lab in rbpf})
    gain = model.log_posterior(mcmc_map) - model.log_posterior(rbpf_map)
    p_mcmc, p_rbpf = (same_place_probabilities(d, model.n)[np.triu_indices(model.n, 1)] for d in (mcmc, rbpf))
    in_play = np.maximum(p_mcmc, p_rbpf) >= 0.01  # pairs either PTM deems possibly one place
    upper = np.abs(p_mcmc - p_rbpf)[in_play]
    return {
        "rbpf_topologies": len(rbpf),
        "tv": total_variation(mcmc, rbpf),
        "tv_reweighted": total_variation(mcmc, reweighted),
        "map_equal": mcmc_map == rbpf_map,
        "map_gain_nats": float(gain),
        "rbpf_map_mass": float(mcmc.get(rbpf_map, 0.0)),
        "rbpf_map_among": rbpf_map in mcmc,
        "pairs_in_play": int(upper.size),
        "pair_max_diff": float(upper.max(initial=0.0)),
        "pair_mean_diff": float(upper.mean()) if upper.size else 0.0,
        "pairs_differing": int(np.count_nonzero(upper > 0.1)),
    }


def _json_state(state: Any) -> Any:
    """An MCMC state (an integer id or a label sequence) as plain JSON values."""
    if isinstance(state, Iterable) and not isinstance(state, str | bytes):
        return [int(v) for v in state]
    return int(state)


def cold_chain_details(res: Any) -> dict[str, Any]:
    """The cold-chain states of an MCMC result for the report's SRQ plot
    (``ptm_ros.reporting.chain_trace.SRQ_KEY``), one list per chain, their thinning stride and the topology
    of each state id (when known); nothing when the result holds none. ``ptm-run`` keeps only their summary
    in ptm.json (:func:`ptm_ros.reporting.chain_trace.split_chain_trace`)."""
    chains = [list(c) for c in getattr(res, "cold_states", ()) if len(c)]
    if not chains:
        return {}
    out = {
        "cold_chain_states": [[_json_state(s) for s in c] for c in chains],
        "cold_chain_thin": int(getattr(res, "cold_thin", 1)),
    }
    labels = getattr(res, "state_labels", None)
    if labels:
        out["cold_chain_labels"] = [_json_state(lab) for lab in labels]
    return out
