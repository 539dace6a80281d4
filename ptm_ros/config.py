"""The root configuration of ptm_ros: one frozen dataclass per concern under :class:`PtmConfig`.

Defaults are inline in each concern's dataclass; ``config/ptm.yaml`` lists them for users; a YAML file
given with ``--params`` overrides any subset (strictly: unknown keys and bad values are errors naming the
field). The configuration actually used is saved beside every result (``DIR/config.yaml``).
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ptm_ros.configio import from_dict, load_yaml, to_dict
from ptm_ros.errors import ConfigError
from ptm_ros.inference.mcmc import McmcConfig
from ptm_ros.maps.mapping import MappingConfig
from ptm_ros.maps.occupancy import OccupancyConfig
from ptm_ros.maps.refinement import RefinementConfig
from ptm_ros.maps.routes import RouteConfig
from ptm_ros.model.posterior import ModelConfig
from ptm_ros.perception.detectors import EquidistantConfig, PlacedLandmarksConfig
from ptm_ros.perception.laser import LaserConfig
from ptm_ros.perception.laser_odometry import LaserOdometryConfig
from ptm_ros.perception.surprise import AppearanceSurpriseConfig, LaserSurpriseConfig

METHODS = ("exact", "rbpf", "mcmc")
DETECTORS = ("equidistant", "laser-surprise", "appearance-surprise", "ground-truth")


@dataclass(frozen=True)
class TopicsConfig:
    """Topic names read from bags (and subscribed to by the nodes)."""

    odom: str = "/odom"
    scan: str = "/scan"
    panorama: str = "/panorama"


@dataclass(frozen=True)
class DetectorConfig:
    """Which landmark detector to use; None = the default for the bag's sensors. ``ground-truth`` fires where
    the true path passes landmarks fixed in the environment
    (:class:`ptm_ros.perception.detectors.PlacedLandmarksConfig`, the thesis' Intel protocol), offline only:
    it needs the run's ground truth."""

    kind: str | None = None
    equidistant: EquidistantConfig = field(default_factory=EquidistantConfig)
    ground_truth: PlacedLandmarksConfig = field(default_factory=PlacedLandmarksConfig)
    laser_surprise: LaserSurpriseConfig = field(default_factory=LaserSurpriseConfig)
    appearance_surprise: AppearanceSurpriseConfig = field(default_factory=AppearanceSurpriseConfig)
    vocabulary: str | None = None  # .npz of a SIFT vocabulary (ptm_ros.model.vocabulary) for words models
    image_max_dt: float = 1.0  # s: a visit takes the signature of the panorama nearest in time, within this

    def __post_init__(self) -> None:
        if self.kind is not None and self.kind not in DETECTORS:
            msg = f"detector kind must be one of {DETECTORS}, got {self.kind!r}"
            raise ConfigError(msg)
        if not self.image_max_dt > 0:
            msg = f"image_max_dt must be > 0, got {self.image_max_dt}"
            raise ConfigError(msg)


@dataclass(frozen=True)
class InferenceConfig:
    """Which estimator computes the PTM, and its budget."""

    method: str = "rbpf"
    particles: int = 100
    resample: str = "optimal"  # RBPF: "optimal" (Fearnhead-Clifford) or "top"
    seed: int = 0
    top: int = 50  # topologies written to ptm.json
    timeline: int = 3  # rbpf: topologies per visit in ptm.json's inference.timeline (0: no timeline)
    greedy: bool = False  # also run the greedy single-answer baseline (a pose graph per visit: O(N²))
    max_exact_visits: int = 9  # exact enumeration refuses larger N (B_9 = 21 147; B_12 = 4.2 million)
    mcmc: McmcConfig = field(default_factory=McmcConfig)

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            msg = f"inference method must be one of {METHODS}, got {self.method!r}"
            raise ConfigError(msg)
        if self.resample not in ("optimal", "top"):
            msg = f"inference resample must be 'optimal' or 'top', got {self.resample!r}"
            raise ConfigError(msg)
        if self.particles < 1 or self.top < 1:
            msg = f"particles and top must be >= 1, got {self.particles}, {self.top}"
            raise ConfigError(msg)
        if self.timeline < 0:
            msg = f"inference timeline must be >= 0 (topologies per visit), got {self.timeline}"
            raise ConfigError(msg)
        if not 1 <= self.max_exact_visits <= 12:
            msg = f"max_exact_visits must be in 1..12, got {self.max_exact_visits}"
            raise ConfigError(msg)
        if isinstance(self.seed, bool) or not isinstance(self.seed, numbers.Integral) or self.seed < 0:
            msg = f"inference seed must be an integer >= 0, got {self.seed!r}"
            raise ConfigError(msg)


@dataclass(frozen=True)
class PtmConfig:
    """Everything ptm_ros can be told, one section per concern."""

    model: ModelConfig = field(default_factory=ModelConfig)
    laser: LaserConfig = field(default_factory=LaserConfig)
    laser_odometry: LaserOdometryConfig = field(default_factory=LaserOdometryConfig)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    inference: InferenceConfig = field(default_factory=InferenceConfig)
    topics: TopicsConfig = field(default_factory=TopicsConfig)
    occupancy: OccupancyConfig = field(default_factory=OccupancyConfig)  # map.pgm / map.png and /map
    mapping: MappingConfig = field(default_factory=MappingConfig)  # the map publisher's online map
    refinement: RefinementConfig = field(default_factory=RefinementConfig)  # scan matches along revisits
    routes: RouteConfig = field(default_factory=RouteConfig)  # route_graph.geojson's edges around walls


def load_config(path: str | Path | None = None, overrides: dict[str, Any] | None = None) -> PtmConfig:
    """Defaults, then the YAML file at ``path`` (if any), then ``overrides`` (nested dicts) on top.

    The file must be valid on its own: a wrong value in it is an error even where an override replaces it
    (a command-line flag does not hide a broken parameter file).

    The file may be plain (``inference: {method: rbpf}``) or a ROS 2 parameter file
    (``/**: {ros__parameters: {...}}`` and/or per-node sections), so one file serves ``ptm-run`` and the
    nodes; the ``ros__parameters`` of every section are merged in file order.
    """
    data: dict[str, Any] = unwrap_ros_parameters(load_yaml(path)) if path is not None else {}
    if overrides:
        if path is not None:  # the file is checked on its own first: an override does not hide its errors
            try:
                from_dict(PtmConfig, data)
            except ConfigError as err:
                msg = f"{err} (in {path})"
                raise ConfigError(msg) from err
        data = _merge(data, overrides)
    return from_dict(PtmConfig, data)


#: Node-level ROS parameters that are not ptm_ros model configuration (``ptm_ros.nodes.common`` declares
#: them); a parameter file's sections may carry them and ``ptm-run`` ignores them.
ROS_ONLY_PARAMETERS = frozenset(
    {
        "use_sim_time",
        "out_dir",
        "sensor_qos",
        "use_scans",
        "use_images",
        "stall_s",
        "end_timeout",
        "marker_topologies",
        "refit_max_visits",
        "frame_id",
        "stamp_jump_s",
        "jump_confirm",
        "max_speed",
        "silence_s",
        "trace_rows",
        "state_file",
        "autosave_every",
        "resume",
    }
)


def unwrap_ros_parameters(doc: dict[str, Any]) -> dict[str, Any]:
    """The configuration in a ROS 2 parameter file (``<node>: ros__parameters: ...``), or ``doc`` itself."""
    sections = [v for v in doc.values() if isinstance(v, dict) and "ros__parameters" in v]
    if not sections:
        return doc
    if len(sections) != len(doc):
        msg = "a ROS parameter file must have only '<node>: {ros__parameters: ...}' sections at the top"
        raise ConfigError(msg)
    out: dict[str, Any] = {}
    for sec in sections:
        params = sec["ros__parameters"] or {}
        if not isinstance(params, dict):
            msg = "ros__parameters must be a mapping"
            raise ConfigError(msg)
        out = _merge(out, {k: v for k, v in params.items() if k not in ROS_ONLY_PARAMETERS})
    return out


def ros_parameters_yaml(config: PtmConfig | None = None) -> str:
    """The configuration as a ROS 2 parameter file for all nodes (None values left out: ROS parameters
    cannot be null, and a missing key takes its default)."""
    import yaml

    def drop_none(d: Any) -> Any:
        if isinstance(d, dict):
            return {k: drop_none(v) for k, v in d.items() if v is not None}
        return d

    body = drop_none(to_dict(config or PtmConfig()))
    header = (
        "# ptm_ros parameters with their defaults (generated from the config dataclasses by\n"
        "# `python -m ptm_ros.config > config/ptm.yaml`). Use with `ptm-run --params FILE` or\n"
        "# `--ros-args --params-file FILE`; keep only the keys you change.\n"
    )
    return header + yaml.safe_dump({"/**": {"ros__parameters": body}}, sort_keys=False)


def _merge(base: dict[str, Any], top: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in top.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def save_config(config: PtmConfig, path: str | Path) -> Path:
    """Write the configuration used as YAML (loadable again with :func:`load_config`)."""
    import yaml

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(to_dict(config), sort_keys=False))
    return path


if __name__ == "__main__":
    print(ros_parameters_yaml(), end="")
