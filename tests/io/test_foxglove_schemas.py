"""Every JSON Schema the project writes passes the rules of Foxglove's and Lichtblick's parser
(``parseJsonSchema`` in their ``packages/mcap-support/src/parseJsonSchema.ts``), which Python's ``jsonschema``
does not check: a channel whose schema that parser refuses is missing from the client's topic list, so no panel
can show it. ``foxglove_parse`` below follows the TypeScript's type switch case by case (an independent copy,
so the check does not rest on ``mcap_log.foxglove_schema_problems`` being right); the run tests in
test_mcap_log.py validate every message against the same schemas with ``jsonschema``."""

from __future__ import annotations

import copy
import json

import pytest
from mcap.reader import make_reader

from ti_fusion.io.mcap_log import RunLogger, foxglove_schema_problems, json_field, json_object


class Unsupported(Exception):
    """What parseJsonSchema throws (an Error, or a TypeError on an object without properties)."""


def foxglove_parse(schema: dict, type_name: str = "root") -> dict[str, list[tuple[str, str, bool]]]:
    """The datatypes parseJsonSchema builds ({type name: [(field, type, is array)]}), or Unsupported where
    it throws."""
    datatypes: dict[str, list[tuple[str, str, bool]]] = {}

    def add_fields(schema: dict, type_name: str) -> None:
        if schema.get("type") != "object":
            raise Unsupported(f'Expected "type": "object" for schema {type_name}, got {schema.get("type")!r}')
        if not isinstance(schema.get("properties"), dict):  # Object.entries(undefined) throws a TypeError
            raise Unsupported(f"{type_name}: Cannot convert undefined or null to object")
        fields = []
        for name, field in schema["properties"].items():
            kind = field.get("type")
            if kind == "boolean":
                fields.append((name, "bool", False))
            elif kind == "string":
                if field.get("contentEncoding") is None:
                    fields.append((name, "string", False))
                elif field["contentEncoding"] == "base64":
                    fields.append((name, "uint8", True))
                else:
                    raise Unsupported(f"Unsupported contentEncoding {field['contentEncoding']!r}")
            elif kind in ("number", "integer"):
                fields.append((name, "float64", False))
            elif kind == "object":
                add_fields(field, f"{type_name}.{name}")
                fields.append((name, f"{type_name}.{name}", False))
            elif kind == "array":
                items = field.get("items")
                if not isinstance(items, dict):  # itemSchema.type of undefined throws a TypeError
                    raise Unsupported(f"{name}: Cannot read properties of undefined (reading 'type')")
                item_kind = items.get("type")
                if item_kind == "boolean":
                    fields.append((name, "bool", True))
                elif item_kind == "string":
                    if items.get("contentEncoding") is not None:
                        raise Unsupported(f"Unsupported contentEncoding {items['contentEncoding']!r} for array item")
                    fields.append((name, "string", True))
                elif item_kind in ("number", "integer"):
                    fields.append((name, "float64", True))
                elif item_kind == "object":
                    add_fields(items, f"{type_name}.{name}")
                    fields.append((name, f"{type_name}.{name}", True))
                else:
                    raise Unsupported(f"Unsupported array item type: {json.dumps(item_kind)}")
            else:  # "null", a list of types (a union), no type at all
                raise Unsupported(f"Unsupported object field type for {name}: {json.dumps(kind)}")
        datatypes[type_name] = fields

    add_fields(schema, type_name)
    return datatypes


def _stats_schemas() -> dict[str, dict]:
    """Each command's stats schema as the log sink declares it (with ms.load and ms.log)."""
    from ti_fusion.sinks.log import stats_schema
    from ti_fusion.slam.fuse_step import FuseStep
    from ti_fusion.slam.slam_step import SLAMStep
    from ti_fusion.slam.vo_step import VOStep

    return {step.stats_channel: stats_schema(step) for step in (SLAMStep, VOStep, FuseStep)}


@pytest.mark.parametrize("topic", ["/slam/stats", "/vo/stats", "/fuse/stats"])
def test_every_stats_schema_passes_foxglove_parser(topic):
    schema = _stats_schemas()[topic]
    datatypes = foxglove_parse(schema)
    assert foxglove_schema_problems(schema) == []
    assert ("frame", "float64", False) in datatypes["root"]
    if topic == "/slam/stats":  # the fields the shipped layout plots, and the loop's nested records
        root = dict((n, t) for n, t, _ in datatypes["root"])
        assert {"surfels", "icp", "ms"} <= set(root)
        assert ("inlier_ratio", "float64", False) in datatypes["root.icp"]
        assert ("residual_rms_m", "float64", False) in datatypes["root.icp"]
        assert ("candidates", "root.loop.candidates", True) in datatypes["root.loop"]
        assert ("applied", "float64", True) in datatypes["root.loop"]
        assert {"detect", "verify", "correct"} <= {n for n, _, _ in datatypes["root.loop.ms"]}


def test_schemas_written_to_a_log_pass_foxglove_parser(tmp_path):
    """What reaches the file: a declared schema, and the one inferred for an undeclared channel from a
    message with a null, an empty list and a list of lists (left out of the inferred schema)."""
    path = tmp_path / "log.mcap"
    with RunLogger(path) as log:
        log.declare_json("/slam/stats", _stats_schemas()["/slam/stats"])
        log.log_stats(0.0, {"frame": 0, "cond": float("nan"), "none": None, "empty": [], "grid": [[1, 2]],
                            "rows": [{"a": 1, "b": None}], "ok": True}, channel="/x/stats")
    with open(path, "rb") as f:
        schemas = {s.name: json.loads(s.data) for s in make_reader(f).get_summary().schemas.values()
                   if s.encoding == "jsonschema"}
    assert set(schemas) == {"ti_fusion.SlamStats", "ti_fusion.XStats"}
    for schema in schemas.values():
        foxglove_parse(schema)
    assert set(schemas["ti_fusion.XStats"]["properties"]) == {"frame", "rows", "ok"}


# A correct leaf, object and array, then one broken copy per rule the parser enforces.
GOOD = {"type": "object", "properties": {
    "x": {"type": "number"},
    "o": {"type": "object", "properties": {"n": {"type": "integer"}}},
    "a": {"type": "array", "items": {"type": "object", "properties": {"s": {"type": "string"}}}},
}}
BROKEN = {
    "union type": ("x", {"type": ["number", "null"]}),
    "null type": ("x", {"type": "null"}),
    "no type": ("x", {"description": "anything"}),
    "object without properties": ("o", {"type": "object"}),
    "array item object without properties": ("a", {"type": "array", "items": {"type": "object"}}),
    "untyped array": ("a", {"type": "array"}),
    "array of untyped items": ("a", {"type": "array", "items": {}}),
    "array of arrays": ("a", {"type": "array", "items": {"type": "array", "items": {"type": "number"}}}),
    "array of unions": ("a", {"type": "array", "items": {"type": ["number", "null"]}}),
}


def test_the_rules_accept_a_good_schema():
    assert foxglove_parse(GOOD)["root.a"] == [("s", "string", False)]
    assert foxglove_schema_problems(GOOD) == []


@pytest.mark.parametrize("case", list(BROKEN))
def test_the_rules_refuse_each_broken_schema(case, tmp_path):
    """The parser's copy throws, the project's check names the field, and declare_json refuses to write it."""
    name, field = BROKEN[case]
    schema = copy.deepcopy(GOOD)
    schema["properties"][name] = field
    with pytest.raises(Unsupported):
        foxglove_parse(schema)
    problems = foxglove_schema_problems(schema)
    assert len(problems) == 1 and problems[0].startswith(name), problems
    with RunLogger(tmp_path / "log.mcap") as log, pytest.raises(ValueError, match="Foxglove cannot read"):
        log.declare_json("/x/stats", schema)


def test_a_broken_stats_schema_fails_the_rules():
    """The slam schema with one union type put back (icp.residual_rms_m as it was declared before) fails."""
    schema = _stats_schemas()["/slam/stats"]
    schema["properties"]["icp"]["properties"]["residual_rms_m"]["type"] = ["number", "null"]
    with pytest.raises(Unsupported, match="residual_rms_m"):
        foxglove_parse(schema)
    assert foxglove_schema_problems(schema) == ['icp.residual_rms_m: unsupported type ["number", "null"] '
                                                "(one type string per field)"]


@pytest.mark.parametrize("kind, extra", [(["number", "null"], {}), ("object", {}), ("array", {}),
                                         ("array", {"items": {"type": "object"}}), ("null", {})])
def test_the_declaration_helpers_refuse_what_foxglove_cannot_read(kind, extra):
    with pytest.raises(ValueError):
        json_field(kind, "a field", **extra)
    with pytest.raises(ValueError, match="properties"):
        json_object({})


def test_a_loop_keyframes_stats_validate_against_the_declared_schema():
    """The loop entry of /slam/stats (candidates with and without ICP numbers, no loop applied, then one
    applied) validates with jsonschema, after log_stats leaves out the values not measured."""
    import jsonschema
    import numpy as np

    from ti_fusion.io.mcap_log import without_nulls
    from ti_fusion.io.outputs import jsonable
    from ti_fusion.loop.closure import LoopReport
    from ti_fusion.loop.verification import LoopCandidate
    from ti_fusion.slam.dense import FrameResult
    from ti_fusion.slam.slam_step import frame_stats

    validator = jsonschema.Draft202012Validator(_stats_schemas()["/slam/stats"])
    rejected = LoopCandidate(4, 1, 0.31, reason="few_consistent", consistent=12)
    verified = LoopCandidate(4, 0, 0.52, verified=True, reason="verified", consistent=80, pnp_inliers=60,
                             icp_inlier_ratio=0.91, icp_residual_m=0.004, ms=12.5)
    for applied in (None, (0, 4)):
        report = LoopReport(4, "moved", [rejected, verified], applied, "applied" if applied else "",
                            {"keyframe": 0.4, "detect": 1.0, "verify": 20.0, "optimise": 3.0, "correct": 5.0})
        result = FrameResult(index=40, timestamp=2.0, pose=np.eye(4), tracking="ok",
                             ms={"pyramid": 1.0, "track": 9.0, "loop": 29.4}, loop=report)
        message = without_nulls(jsonable(frame_stats(result, 1000)))
        errors = [f"{'.'.join(map(str, e.absolute_path))}: {e.message}" for e in validator.iter_errors(message)]
        assert not errors, errors
        assert message["loop"]["applied"] == ([] if applied is None else [0, 4])
        assert "icp_residual_mm" not in message["loop"]["candidates"][0]
        assert message["loop"]["candidates"][1]["icp_residual_mm"] == 4.0


def test_icp_iterations_in_the_stats_are_coarse_to_fine_as_the_setting():
    """/slam/stats' icp.iterations counts each level's iterations in the order of the setting icp.iterations
    (coarse → fine), not by level number (0 = finest)."""
    import numpy as np

    from ti_fusion.slam.dense import FrameResult
    from ti_fusion.slam.slam_step import frame_stats
    from ti_fusion.tracking.icp import ICPResult, IterationRecord

    icp = ICPResult(pose=np.eye(4), iterations=[IterationRecord(2, i, 1.0, 100) for i in range(4)]
                    + [IterationRecord(1, i, 1.0, 100) for i in range(2)] + [IterationRecord(0, 0, 1.0, 100)])
    result = FrameResult(index=1, timestamp=0.1, pose=np.eye(4), tracking="ok", ms={"pyramid": 1.0}, icp=icp)
    assert frame_stats(result, 10)["icp"]["iterations"] == [4, 2, 1]
