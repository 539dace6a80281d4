"""rosbag2 writer/reader: the ns stamp rule, exact yaw quaternions, round trips, corrupt bags."""

from __future__ import annotations

import math
import shutil
from decimal import ROUND_HALF_EVEN, Decimal
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from ptm_ros.errors import BagError, ConfigError
from ptm_ros.io.bag import (
    IMAGE_TYPE,
    BagWriter,
    iter_raw,
    ns_to_stamp,
    quaternion_to_yaw,
    read_run,
    stamp_to_ns,
    typestore,
    yaw_to_quaternion,
)

STORAGES = ["mcap", "sqlite3"]


# ------------------------------------------------------------------------------------------ stamps


def decimal_ns(t: float) -> int:
    """Independent reference: the exact binary value of t, times 1e9, rounded half to even."""
    return int((Decimal(t) * 10**9).quantize(Decimal(1), rounding=ROUND_HALF_EVEN))


def test_stamp_to_ns_matches_decimal_reference() -> None:
    rng = np.random.default_rng(1)
    stamps = np.concatenate(
        [rng.uniform(0, 3000, 2000), rng.uniform(1.1e9, 1.2e9, 2000), 10 ** rng.uniform(-12, 0, 500)]
    )
    for t in stamps:
        assert stamp_to_ns(float(t)) == decimal_ns(float(t))
    assert stamp_to_ns(0.0) == 0
    assert stamp_to_ns(2.0**31 - 1e-6) == decimal_ns(2.0**31 - 1e-6) < 2**31 * 10**9


def test_stamp_round_trip_is_exact_for_9_decimal_and_epoch_stamps() -> None:
    rng = np.random.default_rng(2)
    for ns in rng.integers(0, 2**22 * 10**9, 5000):  # below 2^22 s a double resolves < 1 ns
        t = float(f"{int(ns) // 10**9}.{int(ns) % 10**9:09d}")
        assert stamp_to_ns(t) == int(ns)  # the decimal's own ns, whatever the double's rounding
        assert ns_to_stamp(stamp_to_ns(t)) == t
    for ns in rng.integers(2**22 * 10**9, 2**31 * 10**9, 5000):  # epoch-like: coarser than 1 ns
        t = float(f"{int(ns) // 10**9}.{int(ns) % 10**9:09d}")
        assert abs(stamp_to_ns(t) - int(ns)) <= 128  # the double itself is off by up to half an ulp
        assert ns_to_stamp(stamp_to_ns(t)) == t


@pytest.mark.parametrize("bad", [-1e-3, math.nan, math.inf, 2.0**31])
def test_stamp_out_of_range(bad: float) -> None:
    with pytest.raises(BagError, match="stamp"):
        stamp_to_ns(bad)


# --------------------------------------------------------------------------------------------- yaw


def test_yaw_quaternion_round_trip_is_bit_exact() -> None:
    rng = np.random.default_rng(3)
    yaws = np.concatenate(
        [
            rng.uniform(-2 * np.pi, 2 * np.pi, 100_000),
            rng.uniform(-1e-6, 1e-6, 5_000),
            rng.choice([-1.0, 1.0], 5_000) * 10 ** rng.uniform(-300, 0.79, 5_000),
        ]
    )
    specials = [0.0, -0.0, math.pi, -math.pi, 2 * math.pi, -2 * math.pi, math.nextafter(math.pi, 4.0)]
    for yaw in [*map(float, yaws), *specials]:
        got = quaternion_to_yaw(*yaw_to_quaternion(yaw))
        assert got == yaw
        assert math.copysign(1.0, got) == math.copysign(1.0, yaw)


def test_yaw_quaternion_is_the_rotation() -> None:
    """Compare with scipy's independent quaternion of a rotation about z."""
    rng = np.random.default_rng(4)
    for yaw in rng.uniform(-2 * np.pi, 2 * np.pi, 2000):
        q = np.array(yaw_to_quaternion(float(yaw)))
        ref = Rotation.from_euler("z", yaw).as_quat()  # (x, y, z, w), w >= 0
        assert abs(np.dot(q, ref)) == pytest.approx(1.0, abs=1e-15)  # same rotation up to sign
        assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-15)
    # yaws beyond 2π are reduced: same rotation, principal angle
    assert quaternion_to_yaw(*yaw_to_quaternion(7.0)) == pytest.approx(7.0 - 2 * math.pi, abs=1e-15)


def test_quaternion_to_yaw_general_rotation() -> None:
    rng = np.random.default_rng(5)
    for _ in range(500):
        yaw, pitch, roll = rng.uniform(-np.pi, np.pi), rng.uniform(-1.2, 1.2), rng.uniform(-np.pi, np.pi)
        x, y, z, w = Rotation.from_euler("ZYX", [yaw, pitch, roll]).as_quat()
        assert quaternion_to_yaw(x, y, z, w) == pytest.approx(yaw, abs=1e-12)


# --------------------------------------------------------------------------------------- round trip


def make_run(rng: np.random.Generator) -> dict:
    n = 40
    stamps = np.round(np.sort(rng.uniform(0, 500, n)), 6)
    stamps[5] = 1134864629.895182  # an epoch stamp among them
    stamps.sort()
    poses = np.column_stack([rng.normal(0, 100, n), rng.normal(0, 100, n), rng.uniform(-np.pi, np.pi, n)])
    poses[0, 2] = math.pi
    poses[1, 2] = 3.17012  # corrected CARMEN logs hold yaws beyond π
    return {
        "stamps": stamps,
        "poses": poses,
        "twists": rng.normal(0, 1, (n, 2)),
        "ranges": [rng.uniform(0, 80, 361) for _ in range(n)],
        "mono": rng.integers(0, 256, (5, 7), dtype=np.uint8),
        "rgb": rng.integers(0, 256, (4, 6, 3), dtype=np.uint8),
    }


def write_run(path: Path, run: dict, storage: str) -> None:
    with BagWriter(path, storage=storage) as w:
        for i, t in enumerate(run["stamps"]):
            w.write_odometry(t, run["poses"][i], run["twists"][i])
            w.write_scan(t, run["ranges"][i], -math.pi / 2, math.pi / 360, 0.0, 81.91)
        w.write_image(run["stamps"][3], run["mono"])
        w.write_image(run["stamps"][4], run["rgb"])
    assert w.counts == {"/odom": 40, "/scan": 40, "/panorama": 2}


@pytest.mark.parametrize("storage", STORAGES)
def test_round_trip(tmp_path: Path, storage: str) -> None:
    run = make_run(np.random.default_rng(6))
    bag = tmp_path / "run"
    write_run(bag, run, storage)
    data = read_run(bag, require=["/odom", "/scan", "/panorama"])
    assert data.topics == {
        "/odom": "nav_msgs/msg/Odometry",
        "/scan": "sensor_msgs/msg/LaserScan",
        "/panorama": "sensor_msgs/msg/Image",
    }
    odo = data.odometry
    assert odo is not None
    assert np.array_equal(odo.stamps, run["stamps"])  # bit-exact
    assert odo.stamps_ns.tolist() == [decimal_ns(float(t)) for t in run["stamps"]]
    assert np.array_equal(odo.poses, run["poses"])  # bit-exact, yaw included
    assert np.array_equal(odo.twists, run["twists"])
    assert (odo.frame_id, odo.child_frame_id) == ("odom", "base_link")
    scans = data.scans
    assert scans is not None
    assert np.array_equal(scans.stamps, run["stamps"])
    assert isinstance(scans.ranges, np.ndarray)
    assert scans.ranges.dtype == np.float32
    assert np.array_equal(scans.ranges, np.array(run["ranges"], dtype=np.float32))
    assert np.all(scans.angle_min == np.float32(-math.pi / 2))
    assert np.all(scans.angle_increment == np.float32(math.pi / 360))
    assert np.all(scans.range_max == np.float32(81.91))
    assert np.all(scans.range_min == 0.0)
    assert scans.frame_id == "base_laser"
    img = data.images
    assert img is not None
    assert img.encodings == ["mono8", "rgb8"]
    assert img.images[0].tobytes() == run["mono"].tobytes()
    assert img.images[0].shape == (5, 7)
    assert np.array_equal(img.images[1], run["rgb"])
    assert np.array_equal(img.stamps, run["stamps"][3:5])
    assert (img.frame_id, img.skipped) == ("camera", {})


@pytest.mark.parametrize("storage", STORAGES)
def test_iter_raw_time_order_and_header_stamps(tmp_path: Path, storage: str) -> None:
    bag = tmp_path / "b"
    with BagWriter(bag, storage=storage) as w:
        # written out of time order on purpose
        w.write_odometry(2.0, (1, 2, 3))
        w.write_scan(1.0, [1.0, 2.0], 0.0, 0.1, 0.0, 10.0)
        w.write_odometry(0.5, (0, 0, 0))
        raw_time = typestore().types["builtin_interfaces/msg/Time"](sec=7, nanosec=5)
        w.write_raw(
            "/clock_like",
            "builtin_interfaces/msg/Time",
            1_500_000_000,
            bytes(typestore().serialize_cdr(raw_time, "builtin_interfaces/msg/Time")),
        )
    msgs = list(iter_raw(bag))
    assert [m.log_time_ns for m in msgs] == [500_000_000, 1_000_000_000, 1_500_000_000, 2_000_000_000]
    assert [m.topic for m in msgs] == ["/odom", "/scan", "/clock_like", "/odom"]
    assert [m.header_stamp_ns for m in msgs] == [500_000_000, 1_000_000_000, None, 2_000_000_000]
    odom = typestore().deserialize_cdr(msgs[-1].rawdata, msgs[-1].msgtype)
    assert odom.pose.pose.position.x == 1.0
    only = list(iter_raw(bag, topics=["/scan"]))
    assert [m.topic for m in only] == ["/scan"]
    with pytest.raises(BagError, match="has no topic /tf"):
        list(iter_raw(bag, topics=["/tf"]))


def test_ragged_scans_and_image_encodings(tmp_path: Path) -> None:
    bag = tmp_path / "b"
    t = typestore().types

    def header(sec: int) -> object:
        return t["std_msgs/msg/Header"](
            stamp=t["builtin_interfaces/msg/Time"](sec=sec, nanosec=0), frame_id="cam"
        )

    img16 = np.array([[1, 258, 65535], [0, 4096, 7]], dtype=">u2")
    padded = np.zeros((2, 8), dtype=np.uint8)
    padded[:, :3] = [[1, 2, 3], [4, 5, 6]]
    messages = [
        t[IMAGE_TYPE](
            header=header(3),
            height=2,
            width=3,
            encoding="mono16",
            is_bigendian=1,
            step=6,
            data=np.frombuffer(img16.tobytes(), dtype=np.uint8),
        ),
        t[IMAGE_TYPE](
            header=header(4),
            height=2,
            width=3,
            encoding="mono8",
            is_bigendian=0,
            step=8,
            data=padded.reshape(-1),
        ),
        t[IMAGE_TYPE](
            header=header(5),
            height=1,
            width=2,
            encoding="yuv422",
            is_bigendian=0,
            step=4,
            data=np.zeros(4, dtype=np.uint8),
        ),
    ]
    with BagWriter(bag) as w:
        w.write_scan(1.0, [1.0, 2.0, 3.0], 0.0, 0.1, 0.0, 10.0)
        w.write_scan(2.0, [1.0, 2.0], 0.0, 0.1, 0.0, 10.0)
        for k, m in enumerate(messages):
            w.write_raw("/panorama", IMAGE_TYPE, 3_000_000_000 + k, typestore().serialize_cdr(m, IMAGE_TYPE))
    data = read_run(bag)
    assert data.odometry is None
    assert isinstance(data.scans.ranges, list)
    assert [r.tolist() for r in data.scans.ranges] == [[1.0, 2.0, 3.0], [1.0, 2.0]]
    images = data.images
    assert images.encodings == ["mono16", "mono8"]
    assert images.skipped == {"yuv422": 1}
    assert data.skipped == {"image-unsupported-encoding": 1}
    assert images.images[0].dtype == np.uint16
    assert images.images[0].tolist() == img16.tolist()
    assert images.images[1].tolist() == [[1, 2, 3], [4, 5, 6]]
    assert images.frame_id == "cam"


# ------------------------------------------------------------------------------------------- errors


@pytest.fixture(scope="module")
def small_bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("bags")
    run = make_run(np.random.default_rng(7))
    bags = {}
    for storage in STORAGES:
        bags[storage] = root / storage
        write_run(bags[storage], run, storage)
    return bags


def corrupted_copy(src: Path, dst: Path, mutate) -> Path:
    shutil.copytree(src, dst)
    storage = next(p for p in dst.iterdir() if p.suffix in (".mcap", ".db3"))
    storage.write_bytes(mutate(storage.read_bytes()))
    return dst


@pytest.mark.parametrize("storage", STORAGES)
@pytest.mark.parametrize("damage", ["truncated", "garbage", "empty"])
def test_corrupt_bag_raises_bag_error(small_bags, tmp_path: Path, storage: str, damage: str) -> None:
    mutate = {
        "truncated": lambda b: b[: len(b) // 2],
        "garbage": lambda b: np.random.default_rng(8).bytes(len(b)),
        "empty": lambda b: b"",
    }[damage]
    bag = corrupted_copy(small_bags[storage], tmp_path / "bad", mutate)
    with pytest.raises(BagError, match=r"bag .*bad") as info:
        read_run(bag)
    assert info.value.__cause__ is not None  # rosbags' error is chained
    with pytest.raises(BagError, match=r"bag .*bad"):
        list(iter_raw(bag))


def test_corrupt_message_data_raises_bag_error(small_bags, tmp_path: Path) -> None:
    """Garbage inside the mcap records (the file structure intact) fails at deserialization: a BagError
    when the storage cannot be read on, else the undecodable message is skipped and counted."""
    src = small_bags["mcap"]
    failures = 0
    for k in range(6):

        def smash(b: bytes, k: int = k) -> bytes:
            start = len(b) // 8 * (k + 1)
            return b[:start] + np.random.default_rng(k).bytes(2000) + b[start + 2000 :]

        bag = corrupted_copy(src, tmp_path / f"bad{k}", smash)
        try:
            run = read_run(bag)
        except BagError:
            failures += 1
        else:
            failures += bool(run.skipped)
    assert failures >= 3  # unreadable storage is a BagError, undecodable messages are counted


def test_missing_bag_and_missing_metadata(tmp_path: Path) -> None:
    with pytest.raises(BagError, match="does not exist"):
        read_run(tmp_path / "nope")
    (tmp_path / "empty_dir").mkdir()
    with pytest.raises(BagError, match=r"empty_dir is not a rosbag2 directory: it has no metadata.yaml$"):
        read_run(tmp_path / "empty_dir")
    (tmp_path / "x.txt").write_text("hello")
    with pytest.raises(BagError, match="cannot open bag"):
        read_run(tmp_path / "x.txt")


def test_missing_required_topic_and_wrong_type(small_bags) -> None:
    bag = small_bags["mcap"]
    with pytest.raises(BagError, match=r"lacks required topic /ground_truth \(topics: \['/odom'"):
        read_run(bag, require=["/odom", "/ground_truth"])
    with pytest.raises(
        BagError, match=r"topic /scan .* has type sensor_msgs/msg/LaserScan, expected nav_msgs"
    ):
        read_run(bag, odom_topic="/scan", scan_topic=None)
    data = read_run(bag, odom_topic="/wheel_odom", image_topic=None)
    assert data.odometry is None
    assert data.images is None
    assert data.scans is not None


def test_writer_errors(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="storage must be one of"):
        BagWriter(tmp_path / "a", storage="rosbag1")  # type: ignore[arg-type]
    (tmp_path / "exists").mkdir()
    with pytest.raises(BagError, match="exists already"):
        BagWriter(tmp_path / "exists").open()
    with BagWriter(tmp_path / "b") as w:
        with pytest.raises(BagError, match=r"image must be \(H, W\) or \(H, W, 3\) uint8"):
            w.write_image(1.0, np.zeros((2, 2), dtype=np.float32))
        with pytest.raises(BagError, match="not a ROS 2 Jazzy type"):
            w.write_raw("/x", "my_msgs/msg/Thing", 0, b"\x00\x01\x00\x00")
        w.write_odometry(1.0, (0, 0, 0))
        with pytest.raises(BagError, match="already carries nav_msgs/msg/Odometry"):
            w.write_scan(1.0, [1.0], 0.0, 0.1, 0.0, 1.0, topic="/odom")
        with pytest.raises(BagError, match="pose must be 3 finite numbers"):
            w.write_odometry(1.0, (0, math.nan, 0))
    with pytest.raises(BagError, match="not open for writing"):
        w.write_odometry(2.0, (0, 0, 0))
    assert read_run(tmp_path / "b").odometry.stamps.tolist() == [1.0]


def test_exception_in_with_block_aborts(tmp_path: Path) -> None:
    bag = tmp_path / "aborted"
    with pytest.raises(RuntimeError, match="boom"), BagWriter(bag) as w:
        w.write_odometry(1.0, (0, 0, 0))
        raise RuntimeError("boom")
    assert bag.is_dir()
    assert not (bag / "metadata.yaml").exists()
