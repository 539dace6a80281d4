"""The JSON Schema of ptm.json (``ptm_ros/schema/ptm.schema.json``): what ptm-run writes validates, every
key it writes is documented there, and the documents CONTRACT.md rules out are refused."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import jsonschema
import pytest

from ptm_ros.model.ptm import SCHEMA, Landmark, make_ptm, ptm_schema, to_json_dict
from ptm_ros.tools import run as run_cli

REPO = Path(__file__).resolve().parents[1]
DEMO_BAG = REPO / "bags" / "demo"

#: CONTRACT.md's example document: the required keys and nothing else.
MINIMAL = {
    "schema": "ptm_ros.ptm/1",
    "frame_id": "odom",
    "landmarks": [{"index": k, "stamp": 13.12 + k, "pose": [float(k), 0.0, 0.0]} for k in range(4)],
    "topologies": [{"labels": [0, 1, 2, 0], "probability": 0.91}],
    "inference": {"method": "rbpf", "particles": 100, "seed": 0},
    "timing": {"wall_s": 3.2},
}

#: ptm-run's options and parameters per method, the fastest that exercise it on the demo bag: MCMC
#: started from the filter (so ``inference.versus_rbpf``), exact enumeration over the few visits of a wide
#: equidistant spacing; the particle filter's is ``make demo``'s run with the map (so ``map_quality``), the
#: report and config/demo.yaml (``conftest.demo_run``, which other tests read too).
RUNS: dict[str, tuple[tuple[str, ...], dict[str, Any]]] = {
    "mcmc": (("--method", "mcmc", "--no-report", "--no-map"), {"inference": {"mcmc": {"initial": "rbpf"}}}),
    "exact": (
        ("--method", "exact", "--detector", "equidistant", "--no-report", "--no-map"),
        {"detector": {"equidistant": {"spacing": 18.0}}},  # 6 visits of the demo bag
    ),
}


@pytest.fixture(scope="module")
def validator() -> jsonschema.protocols.Validator:
    schema = ptm_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def errors(validator: jsonschema.protocols.Validator, doc: Any) -> list[str]:
    """The schema's complaints about ``doc``, one line each with the JSON path."""
    return [f"{e.json_path}: {e.message:.200}" for e in validator.iter_errors(doc)]


def _resolve(node: dict[str, Any], root: dict[str, Any]) -> dict[str, Any]:
    while "$ref" in node:
        target = root["$defs"][node["$ref"].removeprefix("#/$defs/")]
        node = {**target, **{k: v for k, v in node.items() if k != "$ref"}}
    return node


def _branch(value: Any, node: dict[str, Any], root: dict[str, Any]) -> dict[str, Any]:
    """The ``oneOf`` branch of ``node`` for ``value``'s JSON type (``node`` itself without one)."""
    if "oneOf" not in node:
        return node
    kind = "object" if isinstance(value, dict) else "array" if isinstance(value, list) else None
    branches = [_resolve(b, root) for b in node["oneOf"]]
    return next((b for b in branches if b.get("type") == kind), {})


def undocumented(value: Any, node: dict[str, Any], root: dict[str, Any], where: str = "$") -> list[str]:
    """Paths of the keys in ``value`` that its schema ``node`` allows but does not name (growth the
    schema permits, but that ptm_ros's own writers must document). Objects whose keys are open by design
    (``additionalProperties`` a schema: counters by reason, acceptance by move) are not keys to name."""
    node = _branch(value, _resolve(node, root), root)
    if isinstance(value, dict):
        named, rest = node.get("properties", {}), node.get("additionalProperties", True)
        out = []
        for key, item in value.items():
            if key in named or isinstance(rest, dict):
                out += undocumented(item, named.get(key, rest), root, f"{where}.{key}")
            else:
                out.append(f"{where}.{key}")
        return out
    if isinstance(value, list) and isinstance(node.get("items"), dict):
        return [
            p
            for k, item in enumerate(value)
            for p in undocumented(item, node["items"], root, f"{where}[{k}]")
        ]
    return []


def run_demo(method: str, out: Path) -> dict[str, Any]:
    """ptm.json of ptm-run on the demo bag with :data:`RUNS`' options for ``method``."""
    options, params = RUNS[method]
    params_file = out.parent / f"{method}.yaml"
    params_file.write_text(json.dumps(params))  # JSON is YAML
    argv = [str(DEMO_BAG), "--out", str(out), "--quiet", "--params", str(params_file), *options]
    assert run_cli.main(argv) == 0
    return json.loads((out / "ptm.json").read_text())


@pytest.mark.slow
@pytest.mark.parametrize("method", sorted([*RUNS, "rbpf"]))
def test_ptm_run_output_validates_and_is_documented(method, validator, tmp_path, capsys, request):
    if method == "rbpf":
        doc = json.loads((request.getfixturevalue("demo_run")[1] / "ptm.json").read_text())
    else:
        doc = run_demo(method, tmp_path / "out")
    capsys.readouterr()
    assert doc["inference"]["method"] == method
    assert "doubts" in doc and "diagnostics" in doc and "trajectory_error" in doc  # the demo has its truth
    assert ("map_quality" in doc) == (method == "rbpf")
    assert ("versus_rbpf" in doc["inference"]) == (method == "mcmc")
    assert errors(validator, doc) == []
    assert undocumented(doc, validator.schema, validator.schema) == []


def test_the_graph_document_ptm_bringup_saves_validates(validator):
    """ptm-bringup's ptm.json is the map publisher's last ``ptm_graph`` document: ptm.json plus
    ``graph_schema``, ``edges`` and ``stream``."""
    topology_filter = pytest.importorskip("ptm_ros.nodes.topology_filter", reason="rclpy not installed")
    from ptm_ros.model.ptm import from_json_dict

    doc = copy.deepcopy(MINIMAL)
    doc["topologies"].append({"labels": [0, 1, 2, 3], "probability": 0.09})
    graph = topology_filter.graph_document(from_json_dict(doc), complete=True)
    assert graph["edges"] and graph["stream"] == {"visits": 4, "complete": True}
    assert errors(validator, graph) == []
    assert undocumented(graph, validator.schema, validator.schema) == []


def test_particle_masses_summing_above_one_by_rounding_are_written_as_one(validator):
    """100 particles of one topology, 0.01 each: their float sum exceeds 1, the written mass does not."""
    particles = [((0, 1, 0), 0.01)] * 100
    assert sum(p for _, p in particles) > 1.0
    landmarks = [Landmark(k, float(k), (float(k), 0.0, 0.0)) for k in range(3)]
    ptm = make_ptm(landmarks, particles, inference=MINIMAL["inference"], timing=MINIMAL["timing"])
    assert ptm.topologies[0].probability == 1.0
    assert errors(validator, to_json_dict(ptm)) == []


def test_the_contract_example_validates(validator):
    assert MINIMAL["schema"] == SCHEMA
    assert errors(validator, MINIMAL) == []
    extended = {**MINIMAL, "novel_key": {"anything": 1}}  # CONTRACT.md: extra keys are welcome
    assert errors(validator, extended) == []


DELETE = object()


def edited(path: str, value: Any) -> dict[str, Any]:
    """:data:`MINIMAL` with the item at the dotted ``path`` (list indices as numbers) set to ``value``, or
    deleted when ``value`` is :data:`DELETE`."""
    doc = copy.deepcopy(MINIMAL)
    *parents, last = (int(p) if p.isdigit() else p for p in path.split("."))
    target: Any = doc
    for p in parents:
        target = target[p]
    if value is DELETE:
        del target[last]
    else:
        target[last] = value
    return doc


@pytest.mark.parametrize(
    ("path", "value", "complaint"),
    [
        ("topologies", DELETE, "'topologies' is a required property"),
        ("inference.seed", DELETE, "'seed' is a required property"),
        ("landmarks.1.pose", DELETE, "'pose' is a required property"),
        ("timing", {}, "'wall_s' is a required property"),
        ("topologies.0.probability", 1.5, "1.5 is greater than the maximum of 1"),
        ("topologies.0.probability", -0.1, "-0.1 is less than the minimum of 0"),
        ("topologies.0.probability", "0.91", "'0.91' is not of type 'number'"),
        ("landmarks.0.stamp", "13.12", "'13.12' is not of type 'number'"),
        ("landmarks.0.pose", [0.0, 0.0], "is too short"),
        ("topologies.0.labels", [1, 0, 2, 0], "0 was expected"),
        ("topologies.0.labels", [0, 1.5, 2, 0], "1.5 is not of type 'integer'"),
        ("inference.method", "greedy", "'greedy' is not one of"),
        ("schema", "ptm_ros.ptm/2", "'ptm_ros.ptm/1' was expected"),
        ("landmarks.0.heading", 0.0, "Additional properties are not allowed"),
    ],
)
def test_documents_the_contract_rules_out_fail(validator, path, value, complaint):
    found = errors(validator, edited(path, value))
    assert found and any(complaint in e for e in found), found


def test_the_documentation_check_names_unknown_keys(validator):
    doc = edited("inference.novel", 1)
    doc["diagnostics"] = {"skipped": {"any_reason": 2}, "novel_counter": 3}
    schema = validator.schema
    assert undocumented(doc, schema, schema) == ["$.inference.novel", "$.diagnostics.novel_counter"]
    assert undocumented(MINIMAL, schema, schema) == []


def test_the_timeline_and_the_greedy_answer_round_trip_and_bad_ones_are_refused(validator):
    """Issue #25: ``inference.timeline`` (the filter's PTM after each visit) and ``greedy`` (the greedy
    baseline's labels) validate, read back as written, and malformed ones fail with the field named."""
    from ptm_ros.errors import DataError
    from ptm_ros.model.ptm import (
        TimelineStep,
        from_json_dict,
        greedy_dict,
        ptm_greedy,
        ptm_timeline,
        timeline_list,
    )

    steps = (
        TimelineStep(1, (((0,), 1.0),)),
        TimelineStep(2, (((0, 1), 0.7), ((0, 0), 0.3))),
        TimelineStep(3, (((0, 1, 0), 0.6), ((0, 1, 2), 0.4))),
        TimelineStep(4, (((0, 1, 2, 0), 0.91),)),
    )
    doc = copy.deepcopy(MINIMAL)
    doc["inference"]["timeline"] = timeline_list(steps)
    doc["greedy"] = greedy_dict((0, 1, 0, 0), 0.99)
    assert doc["greedy"] == {"labels": [0, 1, 0, 0], "places": 2, "gate_probability": 0.99}
    assert errors(validator, doc) == [] and undocumented(doc, validator.schema, validator.schema) == []
    ptm = from_json_dict(json.loads(json.dumps(doc)))
    assert ptm_timeline(ptm) == steps and ptm_greedy(ptm) == (0, 1, 0, 0)
    assert ptm_timeline(from_json_dict(MINIMAL)) == () and ptm_greedy(from_json_dict(MINIMAL)) is None
    for edit, match in (
        (lambda d: d["inference"]["timeline"].pop(0), "timeline step 0 is for 2 visits, expected 1"),
        (
            lambda d: d["inference"]["timeline"][2]["topologies"][0].update(labels=[0, 2, 0]),
            "not a canonical",
        ),
        (lambda d: d["inference"]["timeline"][1]["topologies"][0].update(probability=1.5), "outside"),
        (lambda d: d["inference"]["timeline"][1].pop("topologies"), "KeyError"),
    ):
        bad = copy.deepcopy(doc)
        edit(bad)
        with pytest.raises(DataError, match=match):
            ptm_timeline(from_json_dict(bad))
    for labels in ([0, 1, 0], [1, 0, 0, 0]):
        bad = {**copy.deepcopy(doc), "greedy": {**doc["greedy"], "labels": labels}}
        with pytest.raises(DataError, match="greedy: labels"):
            ptm_greedy(from_json_dict(bad))
