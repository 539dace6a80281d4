"""The streaming visit extractor: same visits whatever the interleaving; codec; bad input."""

from __future__ import annotations

import json
import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
import pytest
from run_cache import once_per_run

from ptm_ros.errors import DataError, ModelError
from ptm_ros.inference.persistence import visit_from_state, visit_to_state
from ptm_ros.io.simulator import SimConfig, simulate
from ptm_ros.io.worlds import get_world
from ptm_ros.model.appearance import AppearanceConfig, panorama_signature
from ptm_ros.model.geometry import between, interpolate_poses, path_length, wrap_angle
from ptm_ros.model.visits import Visit
from ptm_ros.perception.detectors import Detector, EquidistantConfig, EquidistantDetector
from ptm_ros.perception.landmarks import (
    LANDMARK_DROPS,
    ExtractorConfig,
    VisitExtractor,
    landmark_accounting,
    visit_from_json,
    visit_to_json,
)
from ptm_ros.perception.laser import LaserConfig
from ptm_ros.perception.laser_odometry import LaserOdometryConfig


@pytest.fixture(scope="module")
def sim():
    return simulate(get_world("t-junction"), SimConfig(), np.random.default_rng(9), visits=5)


#: The simulated laser the messages' ranges come from (angles and range limits for ``on_scan``).
LASER = SimConfig().laser


def messages(sim):
    odom = [("o", float(t), p) for t, p in zip(sim.odom_stamps, sim.odom_poses, strict=True)]
    scans = [("s", float(t), r) for t, r in zip(sim.scan_stamps, sim.scan_ranges, strict=True)]
    images = [("i", float(t), im) for t, im in zip(sim.image_stamps, sim.images, strict=True)]
    return odom, scans, images, LASER


def run_extractor(streams, cfg, order, spacing=4.0, laser_odometry=None, config=None, patches=None):
    ext = VisitExtractor(
        EquidistantDetector(EquidistantConfig(spacing=spacing)),
        laser=LaserConfig(),
        config=config or ExtractorConfig(),
        laser_odometry=laser_odometry,
        patches=patches,
    )
    out = []
    for kind, t, payload in order:
        if kind == "o":
            out += ext.on_odometry(t, payload)
        elif kind == "s":
            out += ext.on_scan(t, payload, cfg.angle_min, cfg.angle_increment, cfg.range_min, cfg.range_max)
        else:
            out += ext.on_image(t, payload)
    return out + ext.flush(), ext


@pytest.fixture(scope="module")
def merged(sim):
    """The run's messages in (stamp, topic) order."""
    odom, scans, images, _ = messages(sim)
    return sorted(odom + scans + images, key=lambda m: (m[1], "osi".index(m[0])))


def visits_and_counters(sim, merged, **options):
    """The visits of ``merged`` and the extractor's diagnostics (:func:`run_extractor`'s ``options``)."""
    visits, ext = run_extractor(None, LASER, merged, **options)
    return visits, ext.diagnostics


@pytest.fixture(scope="module")
def reference(sim, merged, tmp_path_factory):
    """The visits and diagnostics of :func:`merged` at the defaults, laser odometry on."""
    return once_per_run(tmp_path_factory, f"{__name__}.reference", lambda: visits_and_counters(sim, merged))


@pytest.fixture(scope="module")
def raw(sim, merged, tmp_path_factory):
    """The visits and diagnostics of :func:`merged` with the laser odometry off."""
    off = LaserOdometryConfig(enabled=False)
    return once_per_run(
        tmp_path_factory, f"{__name__}.raw", lambda: visits_and_counters(sim, merged, laser_odometry=off)
    )


def interleave(streams, rng, max_lead):
    """A random arrival order: each topic in order, topics running ahead of each other by < max_lead s."""
    idx = [0] * len(streams)
    order = []
    while any(i < len(s) for i, s in zip(idx, streams, strict=True)):
        live = [k for k, s in enumerate(streams) if idx[k] < len(s)]
        heads = [streams[k][idx[k]][1] for k in live]
        oldest = min(heads)
        ok = [k for k, h in zip(live, heads, strict=True) if h - oldest < max_lead]
        k = ok[int(rng.integers(len(ok)))]
        order.append(streams[k][idx[k]])
        idx[k] += 1
    return order


def assert_same_visits(a, b):
    assert len(a) == len(b)
    for u, v in zip(a, b, strict=True):
        assert (u.index, u.stamp, u.pose, u.travel, u.rotation) == (
            v.index,
            v.stamp,
            v.pose,
            v.travel,
            v.rotation,
        )
        assert np.array_equal(u.signature, v.signature)
        assert np.array_equal(u.patch, v.patch)
        assert np.array_equal(u.signature_spread, v.signature_spread)


@pytest.mark.slow
def test_visits_do_not_depend_on_arrival_order(sim, reference):
    odom, scans, images, cfg = messages(sim)
    reference, _ = reference
    assert len(reference) >= 4
    for seed in range(3):
        order = interleave([odom, scans, images], np.random.default_rng(seed), max_lead=3.0)
        visits, ext = run_extractor(None, cfg, order)
        assert_same_visits(reference, visits)
        assert ext.diagnostics.skipped == {}


@pytest.mark.slow
def test_patches_built_elsewhere_give_the_same_visits(sim, merged, reference):
    """With ``patches`` (here a thread whose every patch takes a while) the extractor goes on while a
    patch is built and returns each visit once its patch is ready: the same visits, in the same order,
    with the same counters as building them in place."""
    cfg = LASER
    reference, ref_diagnostics = reference
    submitted = []

    class SlowPool:
        def __init__(self, pool):
            self.pool = pool

        def submit(self, fn, /, *args, **kwargs):
            submitted.append(fn.__name__)
            return self.pool.submit(lambda: (time.sleep(0.05), fn(*args, **kwargs))[1])

    with ThreadPoolExecutor(max_workers=1) as pool:
        visits, ext = run_extractor(None, cfg, merged, patches=SlowPool(pool))
    assert len(reference) >= 4 and submitted == ["passage_patch"] * len(reference)
    assert_same_visits(reference, visits)
    assert ext.diagnostics == ref_diagnostics


@pytest.mark.slow
def test_visit_content(sim, raw):
    visits, diagnostics = raw
    stamps = list(sim.odom_stamps)
    prev = None
    for v in visits:
        k = stamps.index(v.stamp)
        assert v.pose == tuple(sim.odom_poses[k])  # an odometry sample, unchanged without laser odometry
        assert v.signature is not None and v.patch is not None
        # the patch is expressed in the visit frame: its points surround the origin within the max range
        assert np.all(np.hypot(*v.patch.T) <= LaserConfig().max_range + LaserConfig().patch_radius)
        if prev is not None:
            assert math.isclose(v.travel, path_length(sim.odom_poses[prev : k + 1]), rel_tol=1e-12)
            assert 4.0 <= v.travel < 4.2
        prev = k
    assert diagnostics.visits == len(visits)


@pytest.mark.slow
def test_laser_odometry_corrects_the_visit_poses(sim, reference, raw):
    """With scans, visit poses are the odometry corrected by scan matching: the relative poses between
    consecutive visits are closer to the truth than the wheel odometry's, and the firing stamps agree."""
    scans = messages(sim)[1]
    (corrected, diagnostics), (raw, _) = reference, raw
    counters = diagnostics.laser_odometry
    assert counters["matched"] + counters["gated"] > 0.9 * len(scans)  # matched or inside the motion gate
    stamps = list(sim.odom_stamps)

    def errors(visits):
        k = [stamps.index(v.stamp) for v in visits]
        est = between(np.array([v.pose for v in visits[:-1]]), np.array([v.pose for v in visits[1:]]))
        true = between(sim.true_poses[k[:-1]], sim.true_poses[k[1:]])
        return np.hypot(*(est[:, :2] - true[:, :2]).T), np.abs(wrap_angle(est[:, 2] - true[:, 2]))

    xy_c, th_c = errors(corrected)
    xy_r, th_r = errors(raw)
    assert len(corrected) >= 4
    assert np.sqrt(np.mean(xy_c**2)) < 0.7 * np.sqrt(np.mean(xy_r**2))
    assert np.sqrt(np.mean(th_c**2)) < np.sqrt(np.mean(th_r**2))


@pytest.mark.slow
def test_the_motion_gate_keeps_the_visits():
    """At robot rates (odometry 100 Hz, scans 40 Hz) the laser odometry matches only the scans past its
    motion gate (about one in three) and the visits stay those of matching every scan: visits every 2 s
    (the same odometry samples) whose relative poses agree to the scan matcher's own noise (each
    variant's correction random-walks on its own, so absolute poses drift apart by a few cm), both far
    better than the wheel odometry's, through straight driving and a turn in place."""
    from ptm_ros.io.simulator import CameraConfig
    from ptm_ros.io.simulator import LaserConfig as SimLaser

    config = SimConfig(odom_rate=100.0, laser=SimLaser(rate=40.0), camera=CameraConfig(enabled=False))
    run = simulate(get_world("t-junction"), config, np.random.default_rng(9), visits=2)
    lc = run.config.laser
    end = run.odom_stamps[0] + 24.0
    merged = sorted(
        [(float(t), 0, k) for k, t in enumerate(run.odom_stamps) if t <= end]
        + [(float(t), 1, k) for k, t in enumerate(run.scan_stamps) if t <= end]
    )

    def visits(laser_odometry):
        detector = EquidistantDetector(EquidistantConfig(spacing=0.0, period=2.0))
        ext = VisitExtractor(
            detector,
            laser=LaserConfig(refine=False),  # the patches are not compared here: skip their ICP
            config=ExtractorConfig(use_images=False),
            laser_odometry=laser_odometry,
        )
        out = []
        for t, topic, k in merged:
            if topic == 0:
                out += ext.on_odometry(t, run.odom_poses[k])
            else:
                r = run.scan_ranges[k]
                out += ext.on_scan(t, r, lc.angle_min, lc.angle_increment, lc.range_min, lc.range_max)
        return out + ext.flush(), ext.diagnostics.laser_odometry

    every, every_counters = visits(LaserOdometryConfig(match_xy=0.0, match_yaw=0.0))
    gated, gated_counters = visits(LaserOdometryConfig())
    scans = sum(topic == 1 for _, topic, _ in merged)
    assert every_counters["gated"] == 0 and every_counters["matched"] > 0.9 * scans
    assert gated_counters["gated"] > 0.5 * scans and gated_counters["matched"] > 0.2 * scans
    assert len(every) >= 10
    assert [v.stamp for v in gated] == [v.stamp for v in every]
    k = [list(run.odom_stamps).index(v.stamp) for v in every]
    assert np.ptp(np.unwrap(run.true_poses[k, 2])) > 2.0  # the window includes a turn
    true = between(run.true_poses[k[:-1]], run.true_poses[k[1:]])
    wheel = between(run.odom_poses[k[:-1]], run.odom_poses[k[1:]])

    def steps(vs):
        return between(np.array([v.pose for v in vs[:-1]]), np.array([v.pose for v in vs[1:]]))

    diff = steps(gated) - steps(every)
    assert np.max(np.hypot(diff[:, 0], diff[:, 1])) < 0.05
    assert np.max(np.abs(wrap_angle(diff[:, 2]))) < 0.02
    wheel_error = np.sqrt(np.mean(np.sum(np.square(wheel[:, :2] - true[:, :2]), axis=1)))
    for est in (steps(gated), steps(every)):
        assert np.sqrt(np.mean(np.sum(np.square(est[:, :2] - true[:, :2]), axis=1))) < 0.5 * wheel_error


def test_bad_input_is_counted_not_raised():
    ext = VisitExtractor(EquidistantDetector(EquidistantConfig(spacing=4.0)))
    ext.on_odometry(0.0, (0.0, math.nan, 0.0))
    ext.on_odometry(10.0, (0.0, 0.0, 0.0))
    ext.on_odometry(5.0, (0.0, 0.0, 0.0))  # backwards
    ext.on_scan(10.0, [1.0, 2.0], 0.0, -0.1, 0.0, 10.0)  # negative increment: malformed
    ext.on_image(10.0, np.zeros((4, 4, 4), dtype=np.uint8))  # undecodable (4 channels)
    ext.flush()
    skipped = ext.diagnostics.skipped
    assert skipped["odometry-non-finite"] == 1
    assert skipped["odometry-stamp-backwards"] == 1
    assert skipped.get("scan-malformed", 0) + skipped.get("image-undecodable", 0) >= 1


def test_rewind_drops_a_topic_stretch_stamped_ahead_and_takes_its_messages_again():
    """VisitExtractor.rewind: scans queued on a clock ahead of the odometry's are dropped (counted as
    scan-off-clock) and the topic's next scans, earlier than those, are taken, not skipped as going
    back; a scan before the stream's position stays late; the odometry cannot be rewound."""
    ext = VisitExtractor(
        EquidistantDetector(EquidistantConfig(spacing=4.0)), config=ExtractorConfig(use_images=False)
    )
    scan = ([1.0, 2.0, 3.0], -0.1, 0.1, 0.05, 10.0)
    for k in range(5):
        ext.on_odometry(float(k), (0.5 * k, 0.0, 0.0))
    for k in range(3):
        ext.on_scan(100.0 + k, *scan)  # ahead: queued until the odometry gets there
    ext.on_scan(4.5, *scan)
    assert ext.diagnostics.skipped == {"scan-stamp-backwards": 1}
    assert ext.rewind("scan") == 3
    ext.on_scan(2.0, *scan)  # behind what the odometry has been processed to: late
    for k in range(5, 8):
        ext.on_odometry(float(k), (0.5 * k, 0.0, 0.0))
        ext.on_scan(k + 0.5, *scan)
    ext.flush()
    assert ext.diagnostics.received["scan"] == 8
    assert ext.diagnostics.skipped == {"scan-stamp-backwards": 1, "scan-off-clock": 3, "scan-late": 1}
    with pytest.raises(ModelError, match="only the scan and image topics"):
        ext.rewind("odometry")


def test_odometry_beyond_any_run_is_counted_not_raised():
    """Finite but absurd odometry (a corrupt bag): coordinates beyond visits.MAX_COORDINATE are skipped,
    and a visit after a travel beyond visits.MAX_TRAVEL is dropped; the visits after it are numbered on."""
    ext = VisitExtractor(EquidistantDetector(EquidistantConfig(spacing=4.0)))
    out = ext.on_odometry(0.0, (0.0, 0.0, 0.0))
    out += ext.on_odometry(1.0, (2e7, 0.0, 0.0))
    for k, y in enumerate((0.0, 1.0, 10.0)):
        out += ext.on_odometry(2.0 + k, (9e6, y, 0.0))
    out += ext.flush()
    expected = [(0, (0.0, 0.0, 0.0), 0.0), (1, (9e6, 10.0, 0.0), 10.0)]
    assert [(v.index, v.pose, v.travel) for v in out] == expected
    assert ext.diagnostics.skipped == {"odometry-out-of-range": 1, "visit-invalid": 1}


@pytest.mark.slow
def test_buffers_stay_bounded_on_a_long_run(sim):
    odom, scans, _, cfg = messages(sim)
    # buffers of the extractor itself: laser odometry (a bounded window) and the patches' ICP off for speed
    ext = VisitExtractor(
        EquidistantDetector(EquidistantConfig(spacing=2.0)),
        laser=LaserConfig(refine=False),
        config=ExtractorConfig(use_images=False),
        laser_odometry=LaserOdometryConfig(enabled=False),
    )
    sizes = []
    for lap in range(6):  # replay the run 6 times, shifted in time and space so that stamps increase
        shift = lap * (sim.odom_stamps[-1] - sim.odom_stamps[0] + 1.0)
        seq = sorted(
            [("o", t + shift, p + np.array([lap * 100.0, 0.0, 0.0])) for _, t, p in odom]
            + [("s", t + shift, r) for _, t, r in scans],
            key=lambda m: (m[1], m[0] != "o"),
        )
        for kind, t, payload in seq:
            if kind == "o":
                ext.on_odometry(t, payload)
            else:
                ext.on_scan(t, payload, cfg.angle_min, cfg.angle_increment, cfg.range_min, cfg.range_max)
        sizes.append((len(ext._odom_t), len(ext._scans)))
    assert sizes[-1][0] <= 2 * sizes[1][0] + 10 and sizes[-1][1] <= 2 * sizes[1][1] + 10


@pytest.mark.slow
def test_signature_spread_against_the_panorama_one_place_width_away(sim, merged, raw):
    cfg = LASER
    target = 0.9
    no_lo = LaserOdometryConfig(enabled=False)
    visits, _ = run_extractor(
        None, cfg, merged, laser_odometry=no_lo, config=ExtractorConfig(spread_distance=target)
    )
    without, _ = raw
    assert all(v.signature_spread is None for v in without)  # spread_distance 0: none
    with_spread = [v for v in visits if v.signature_spread is not None]
    assert len(with_spread) >= len(visits) - 1
    t_img = np.asarray(sim.image_stamps)
    xy_img = interpolate_poses(sim.odom_stamps, sim.odom_poses, t_img)[:, :2]
    sigs = [panorama_signature(im, AppearanceConfig()) for im in sim.images]
    for v in with_spread:
        j = int(np.argmin(np.abs(t_img - v.stamp)))
        dist = np.hypot(*(xy_img - xy_img[j]).T)
        ok = (dist >= 0.5 * target) & (dist <= 2.0 * target)
        k = int(np.argmin(np.where(ok, np.abs(dist - target), np.inf)))
        # brute force over every panorama of the run: the buffered one the extractor chose is this one
        np.testing.assert_allclose(v.signature_spread, 0.5 * (sigs[j] - sigs[k]) ** 2, rtol=1e-12)
        assert np.all(v.signature_spread > 0.0)


@pytest.mark.slow
def test_visit_json_round_trip(sim, merged):
    visits, _ = run_extractor(None, LASER, merged, config=ExtractorConfig(spread_distance=0.9))
    assert any(v.signature_spread is not None for v in visits)
    for v in visits:
        back = visit_from_json(visit_to_json(v))
        assert_same_visits([v], [back])
        assert back.words is None
    with pytest.raises(DataError, match="not JSON"):
        visit_from_json("{")
    with pytest.raises(DataError, match="schema"):
        visit_from_json('{"schema": "other"}')
    with pytest.raises(DataError, match="malformed"):
        visit_from_json('{"schema": "ptm_ros.visit/1", "index": 0}')


#: Every optional field set; arrays little-endian so the pinned JSON is the same on any machine.
FULL_VISIT = Visit(
    index=2,
    stamp=12.5,
    pose=(1.0, -2.0, 0.25),
    travel=3.5,
    rotation=0.75,
    signature=np.array([0.5, -1.25], dtype="<f8"),
    words=np.array([3, 0, 7], dtype="<i8"),
    patch=np.array([[0.0, 1.0], [-1.5, 2.0]], dtype="<f8"),
    odom_pose=(1.5, -2.5, 0.5),
    signature_spread=np.array([0.125, 0.0], dtype="<f8"),
)
BARE_VISIT = Visit(index=0, stamp=0.0, pose=(0.0, 0.0, 0.0))
OPTIONAL = ("odom_pose", "signature", "words", "patch", "signature_spread")
#: visit_to_json(FULL_VISIT) as the codec wrote it before the two visit codecs shared one field list
FULL_JSON = (
    '{"schema": "ptm_ros.visit/1", "index": 2, "stamp": 12.5, "pose": [1.0, -2.0, 0.25], '
    '"odom_pose": [1.5, -2.5, 0.5], "travel": 3.5, "rotation": 0.75, '
    '"signature": {"dtype": "<f8", "shape": [2], "data": "AAAAAAAA4D8AAAAAAAD0vw=="}, '
    '"words": {"dtype": "<i8", "shape": [3], "data": "AwAAAAAAAAAAAAAAAAAAAAcAAAAAAAAA"}, '
    '"patch": {"dtype": "<f8", "shape": [2, 2], "data": "AAAAAAAAAAAAAAAAAADwPwAAAAAAAPi/AAAAAAAAAEA="}, '
    '"signature_spread": {"dtype": "<f8", "shape": [2], "data": "AAAAAAAAwD8AAAAAAAAAAA=="}}'
)
BARE_JSON = (
    '{"schema": "ptm_ros.visit/1", "index": 0, "stamp": 0.0, "pose": [0.0, 0.0, 0.0], "odom_pose": null, '
    '"travel": 0.0, "rotation": 0.0, '
    '"signature": null, "words": null, "patch": null, "signature_spread": null}'
)


def assert_identical(got, expected):
    """Same visit, every optional field included: equal values, same dtypes, None where None."""
    assert got == expected
    for name in OPTIONAL:
        a, b = getattr(got, name), getattr(expected, name)
        if b is None or isinstance(b, tuple):
            assert a == b, name
        else:
            assert a.dtype == b.dtype and np.array_equal(a, b), name


def test_both_visit_codecs_round_trip_every_field():
    for v in (FULL_VISIT, BARE_VISIT):
        assert_identical(visit_from_json(visit_to_json(v)), v)
        assert_identical(visit_from_state(visit_to_state(v)), v)
    # a checkpoint casts lists to the fields' dtypes; a JSON message keeps the dtype it was sent in
    state = visit_to_state(FULL_VISIT)
    back = visit_from_state({**state, "signature": [1, 2], "words": [3.0], "signature_spread": [0, 1]})
    assert back.signature.dtype == np.float64 and back.words.dtype == np.int64
    i32 = visit_from_json(visit_to_json(replace(BARE_VISIT, words=np.ones(2, dtype="<i4"))))
    assert i32.words.dtype == np.dtype("<i4")
    # older checkpoints lack odom_pose and signature_spread; a message may leave out any array …
    old = {k: v for k, v in state.items() if k not in ("odom_pose", "signature_spread")}
    assert_identical(visit_from_state(old), replace(FULL_VISIT, odom_pose=None, signature_spread=None))
    bare = {k: v for k, v in json.loads(FULL_JSON).items() if k not in OPTIONAL}
    assert_identical(visit_from_json(json.dumps(bare)), replace(FULL_VISIT, **dict.fromkeys(OPTIONAL)))
    # … but a checkpoint entry must hold signature, words and patch
    with pytest.raises(DataError, match=r"bad visit entry \(KeyError: 'words'\)"):
        visit_from_state({k: v for k, v in state.items() if k != "words"})
    with pytest.raises(DataError, match="malformed visit message: malformed array in visit JSON"):
        visit_from_json(FULL_JSON.replace("AwAAAAAAAAAAAAAAAAAAAAcAAAAAAAAA", "!"))


def test_visit_codecs_write_the_same_text_and_dicts_as_before():
    assert visit_to_json(FULL_VISIT) == FULL_JSON
    assert visit_to_json(BARE_VISIT) == BARE_JSON
    # the checkpoint form: plain values in this key order, then copies of the arrays
    scalars = {"index": 2, "stamp": 12.5, "pose": [1.0, -2.0, 0.25], "odom_pose": [1.5, -2.5, 0.5]}
    scalars |= {"travel": 3.5, "rotation": 0.75}
    state = visit_to_state(FULL_VISIT)
    assert list(state.items())[:6] == list(scalars.items()) and list(state)[6:] == list(OPTIONAL[1:])
    for name in OPTIONAL[1:]:
        arr, orig = state[name], getattr(FULL_VISIT, name)
        assert arr.dtype == orig.dtype and np.array_equal(arr, orig) and not np.shares_memory(arr, orig)
    bare = {"index": 0, "stamp": 0.0, "pose": [0.0, 0.0, 0.0], "odom_pose": None, "travel": 0.0}
    bare |= {"rotation": 0.0, **dict.fromkeys(OPTIONAL[1:])}
    assert list(visit_to_state(BARE_VISIT).items()) == list(bare.items())


class EveryScan(Detector):
    """Declares a landmark at every scan (a detector firing faster than the odometry is sampled)."""

    def on_scan(self, stamp, ranges, *, angle_min, angle_increment, range_min, range_max):
        return True


def test_landmarks_on_one_odometry_sample_become_one_visit_and_are_accounted_for():
    """Two landmarks nearest to the same odometry sample make one visit; the drop is counted by reason and
    :func:`landmark_accounting` says how many landmarks became visits and why the rest did not."""
    ext = VisitExtractor(EveryScan(), config=ExtractorConfig(use_scans=False, use_images=False))
    out = []
    for k in range(4):  # odometry at 1 Hz, scans at 4 Hz: four landmarks per odometry sample
        out += ext.on_odometry(float(k), (2.0 * k, 0.0, 0.0))
        for j in range(4):
            out += ext.on_scan(k + 0.25 * j + 0.1, [1.0, 1.0], 0.0, 0.1, 0.0, 10.0)
    out += ext.flush()
    skipped = ext.diagnostics.skipped
    declared = 16
    assert len(out) + skipped["landmark-at-same-odometry-sample"] == declared
    line = landmark_accounting(len(out), skipped)
    assert line == (
        f"the detector declared {declared} landmarks and {len(out)} became visits: {declared - len(out)} "
        f"dropped ({declared - len(out)} {LANDMARK_DROPS['landmark-at-same-odometry-sample']} "
        "(landmark-at-same-odometry-sample))"
    )


def test_landmark_accounting():
    assert landmark_accounting(10, {}) is None
    assert landmark_accounting(10, {"scan-malformed": 3}) is None  # input messages, not landmarks
    assert landmark_accounting(10, {}, declared=10) is None
    two = landmark_accounting(10, {"visit-invalid": 1, "landmark-at-same-odometry-sample": 1})
    assert two is not None and two.startswith(
        "the detector declared 12 landmarks and 10 became visits: 2 dropped"
    )
    assert "1 had unusable odometry" in two
    more = landmark_accounting(10, {"visit-invalid": 1}, declared=13)
    assert more is not None and more.endswith("; 2 for no recorded reason)")
    assert "declared 11 landmarks" in str(landmark_accounting(10, {"visit-invalid": 1}, declared=5))
