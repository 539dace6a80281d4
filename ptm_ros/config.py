"""The root configuration of ptm_ros: one frozen dataclass per concern under :class:`PtmConfig`.

Each field is declared once in its concern's dataclass, with its default, its range or choices and its
description (:func:`ptm_ros.settings.setting`): every instance is checked against them, and the nodes'
ROS parameters carry them. ``config/ptm.yaml`` lists the defaults for users; a YAML file given with
``--params`` overrides any subset (strictly: unknown keys and bad values are errors naming the field).
The configuration actually used is saved beside every result (``DIR/config.yaml``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ptm_ros.configio import from_dict, load_yaml, to_dict
from ptm_ros.errors import ConfigError
from ptm_ros.inference.mcmc import McmcConfig
from ptm_ros.inference.resampling import RESAMPLE_METHODS
from ptm_ros.maps.mapping import MappingConfig
from ptm_ros.maps.occupancy import OccupancyConfig
from ptm_ros.maps.refinement import RefinementConfig
from ptm_ros.maps.routes import RouteConfig
from ptm_ros.model.posterior import ModelConfig
from ptm_ros.perception.appearance_surprise import AppearanceSurpriseConfig
from ptm_ros.perception.detectors import EquidistantConfig, PlacedLandmarksConfig
from ptm_ros.perception.laser import LaserConfig
from ptm_ros.perception.laser_odometry import LaserOdometryConfig
from ptm_ros.perception.laser_surprise import LaserSurpriseConfig
from ptm_ros.settings import Settings, commented_yaml, json_schema, setting

METHODS = ("exact", "rbpf", "mcmc")
DETECTORS = ("equidistant", "laser-surprise", "appearance-surprise", "ground-truth")


@dataclass(frozen=True)
class TopicsConfig(Settings):
    """Topic names read from bags (and subscribed to by the nodes)."""

    odom: str = setting(
        "/odom",
        doc=(
            "the odometry (``nav_msgs/Odometry``); a bag must have it (``ptm-bringup`` remaps it onto the "
            "landmark detector's ``odom``)."
        ),
    )
    scan: str = setting(
        "/scan",
        doc=(
            "the laser scans (``sensor_msgs/LaserScan``): patches, laser odometry, the laser-surprise "
            "detector and the map; used when the bag has them (remapped onto the detector's ``scan``)."
        ),
    )
    panorama: str = setting(
        "/panorama",
        doc=(
            "the panoramic images (``sensor_msgs/Image``): the visits' appearance signatures and the "
            "appearance-surprise detector; used when the bag has them (remapped onto the detector's "
            "``panorama``)."
        ),
    )


@dataclass(frozen=True)
class DetectorConfig(Settings):
    """Which landmark detector to use; None = the default for the bag's sensors. ``ground-truth`` fires where
    the true path passes landmarks fixed in the environment
    (:class:`ptm_ros.perception.detectors.PlacedLandmarksConfig`, the thesis' Intel protocol), offline only:
    it needs the run's ground truth."""

    kind: str | None = setting(
        None,
        choices=DETECTORS,
        doc=(
            "the landmark detector; None: ``laser-surprise`` when the run has scans and ``model.use_laser`` "
            "is on, else ``equidistant`` (:func:`ptm_ros.factories.detector_kind`)."
        ),
    )
    equidistant: EquidistantConfig = setting(
        factory=EquidistantConfig,
        doc="the ``equidistant`` detector: a visit every so many metres and/or seconds (Ch. 4.5).",
    )
    ground_truth: PlacedLandmarksConfig = setting(
        factory=PlacedLandmarksConfig,
        doc="the ``ground-truth`` detector: landmarks placed along the true path, and their visits.",
    )
    laser_surprise: LaserSurpriseConfig = setting(
        factory=LaserSurpriseConfig, doc="the ``laser-surprise`` detector (Ch. 4.8)."
    )
    appearance_surprise: AppearanceSurpriseConfig = setting(
        factory=AppearanceSurpriseConfig,
        doc="the ``appearance-surprise`` detector (Ch. 4.7); its ``words`` model needs ``vocabulary``.",
    )
    vocabulary: str | None = setting(
        None,
        doc=(
            "``.npz`` of a SIFT vocabulary (:mod:`ptm_ros.model.vocabulary`) for the appearance-surprise "
            "detector's ``words`` model; None: none."
        ),
    )
    image_max_dt: float = setting(
        1.0, gt=0, doc="a visit takes the signature of the panorama nearest in time, within this [s]."
    )


@dataclass(frozen=True)
class InferenceConfig(Settings):
    """Which estimator computes the PTM, and its budget."""

    method: str = setting(
        "rbpf",
        choices=METHODS,
        doc=(
            "the estimator: ``exact`` enumeration of every topology (up to ``max_exact_visits`` visits), "
            "``rbpf`` the Rao-Blackwellised particle filter, or ``mcmc`` batch sampling over set partitions "
            "(settings in ``mcmc``)."
        ),
    )
    particles: int = setting(
        100,
        ge=1,
        doc=(
            "RBPF: N, the distinct topologies kept after each visit, the fewest with ``particles_max`` (also "
            "in the filter pass that gives MCMC its starts and learns the heading noise)."
        ),
    )
    particles_max: int = setting(
        300,
        ge=0,
        doc=(
            "RBPF, ``optimal`` resampling: the most distinct topologies kept where the posterior is spread, "
            "so that resampling thins at most ``thinned_mass`` of it at random; at or below ``particles`` "
            "(e.g. 0): ``particles`` always. What it buys and costs on the real runs: bench/real_seeds.md."
        ),
    )
    thinned_mass: float = setting(
        0.001,
        ge=0,
        lt=1,
        doc=(
            "RBPF, with ``particles_max``: the probability that optimal resampling may thin at random "
            "(children kept with probability w/c only) before it keeps more than ``particles`` topologies "
            "(:func:`ptm_ros.inference.resampling.particle_count`)."
        ),
    )
    resample: str = setting(
        "optimal",
        choices=RESAMPLE_METHODS,
        doc="RBPF: ``optimal`` (Fearnhead-Clifford) or ``top`` (the N heaviest children, biased).",
    )
    reweight: bool = setting(
        True,
        doc=(
            "rbpf: weigh the topologies the filter keeps with the batch model's metric evidence, an "
            "importance-sampling integral over the whole trajectory, instead of the filter's sequential EKF "
            "estimate, which linearises each heading error where the robot drove; applies while the batch "
            "evidence is sampled (up to ``model.odometry.max_sampled_visits`` visits). The PTM is then the "
            "batch model's posterior over the filter's topologies (``--method exact``'s on small runs); off: "
            "the sequential weights (bench/reweighting.md)."
        ),
    )
    seed: int = setting(
        0,
        ge=0,
        doc=(
            "seed of the random numbers (the filter's resampling, the MCMC chains, the metric likelihood's "
            "importance samples): the same seed, the same result."
        ),
    )
    top: int = setting(50, ge=1, doc="topologies written to ptm.json.")
    timeline: int = setting(
        3, ge=0, doc="rbpf: topologies per visit in ptm.json's inference.timeline (0: no timeline)."
    )
    greedy: bool = setting(
        False, doc="also run the greedy single-answer baseline (a pose graph per visit: O(N²))."
    )
    max_exact_visits: int = setting(
        9,
        ge=1,
        le=12,
        doc="exact enumeration refuses larger N (B_9 = 21 147; B_12 = 4.2 million).",
    )
    mcmc: McmcConfig = setting(
        factory=McmcConfig,
        doc="the ``mcmc`` sampler: proposals, MC³ chains, starts, estimate and stopping rule.",
    )

    @property
    def particles_cap(self) -> int:
        """The most distinct topologies the RBPF may hold after a visit: ``particles_max``, or ``particles``
        when that is not above it."""
        return max(self.particles, self.particles_max)


@dataclass(frozen=True)
class PtmConfig(Settings):
    """Everything ptm_ros can be told, one section per concern."""

    model: ModelConfig = setting(
        factory=ModelConfig,
        doc="the posterior: which measurements enter it, the prior over topologies, the likelihoods.",
    )
    laser: LaserConfig = setting(
        factory=LaserConfig, doc="the visits' laser patches and their registration (scan matching)."
    )
    laser_odometry: LaserOdometryConfig = setting(
        factory=LaserOdometryConfig, doc="the scan-to-map correction of the wheel odometry."
    )
    detector: DetectorConfig = setting(
        factory=DetectorConfig, doc="the landmark detector that turns the input into visits."
    )
    inference: InferenceConfig = setting(
        factory=InferenceConfig, doc="the estimator that computes the PTM, and its budget."
    )
    topics: TopicsConfig = setting(factory=TopicsConfig, doc="the topics read from a bag.")
    occupancy: OccupancyConfig = setting(factory=OccupancyConfig, doc="map.pgm / map.png and /map.")
    mapping: MappingConfig = setting(factory=MappingConfig, doc="the map publisher's online map.")
    refinement: RefinementConfig = setting(factory=RefinementConfig, doc="scan matches along revisits.")
    routes: RouteConfig = setting(factory=RouteConfig, doc="route_graph.geojson's edges around walls.")


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
    """The configuration as a ROS 2 parameter file for all nodes, every parameter preceded by its declared
    description and range as comments (None values left out: ROS parameters cannot be null, and a
    missing key takes its default)."""
    header = (
        "# ptm_ros parameters with their defaults (generated from the configuration's declarations by\n"
        "# `python -m ptm_ros.config > config/ptm.yaml`). Use with `ptm-run --params FILE` or\n"
        "# `--ros-args --params-file FILE`; keep only the keys you change.\n"
    )
    body = commented_yaml(config or PtmConfig(), indent=4)
    return header + "\n".join(["/**:", "  ros__parameters:", *body]) + "\n"


#: Where the JSON schema of a parameter file ships (package data, :func:`params_schema`).
PARAMS_SCHEMA_FILE = ("schema", "params.schema.json")


def params_schema() -> dict[str, Any]:
    """The JSON Schema of a parameter file (the plain form of ``ptm-run --params``; a ROS parameter
    file holds the same under ``/**: ros__parameters:``), from the configuration's declarations."""
    schema = json_schema(PtmConfig, title="ptm_ros parameters")
    schema["$id"] = "urn:ptm_ros:schema:params"
    return schema


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
    import json
    import sys

    if sys.argv[1:] == ["--schema"]:
        print(json.dumps(params_schema(), indent=1, ensure_ascii=False))
    else:
        print(ros_parameters_yaml(), end="")
