"""Wire schemas: strictness, versioning, size limits, JSON Schema export; key layout."""

from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import pytest
from confnav.services.keys import KeyError_, Keys, is_valid_id, validate_id

from confnav import schemas as S

DIAG = S.SolveDiagnostics(
    sweeps=7,
    error_estimate=1e-13,
    wall_time=0.5,
    tol=1e-10,
    nodes=[64],
    boundary_residual=1e-13,
    tol_met=True,
)

SAMPLES: list[S.Message] = [
    S.WorkspaceDefinition(
        ws_id="w1",
        outer=[(-1, -1), (1, -1), (1, 1), (-1, 1)],
        obstacles=[[(0.1, 0.1), (0.2, 0.1), (0.2, 0.2)]],
        anchor=(0.0, 0.0),
    ),
    S.TransformSolution(
        ws_id="w1",
        revision="abc",
        definition_hash="def",
        workspace_hash="ws",
        stamp_ns=1,
        anchor=(0.0, 0.0),
        centers=[(0.1, 0.2)],
        radii=[0.05],
        diagnostics=DIAG,
        coefficients={"nodes": [[0.1, 0.2]], "meta": {"n": 3}},
    ),
    S.WorkspaceDelete(ws_id="w1", stamp_ns=1),
    S.TransformStatus(ws_id="w1", stamp_ns=2, state="failed", definition_hash="h", message="x"),
    S.Goal(robot_id="r1", ws_id="w1", goal=(0.0, 0.0), navfn="kr", k=8.0),
    S.GoalCancel(robot_id="r1", stamp_ns=2),
    S.Pose(robot_id="r1", stamp_ns=3, seq=4, x=0.5, y=-0.5, theta=1.0),
    S.VelocityCommand(robot_id="r1", stamp_ns=5, linear=(0.1, 0.2), pose_seq=4, pose_stamp_ns=3),
    S.RobotStatus(robot_id="r1", stamp_ns=6, state="stopped", reason="stale_pose"),
    S.PoseBatch(
        sim_id="sim",
        stamp_ns=3,
        robot_ids=["r1", "r2"],
        stamps_ns=[3, 3],
        seq=[4, 0],
        x=[0.5, 1.0],
        y=[-0.5, 2.0],
        theta=[1.0, 0.0],
    ),
    S.CommandBatch(
        sim_id="sim",
        stamp_ns=5,
        robot_ids=["r1", "r2"],
        linear=[(0.1, 0.2), (0.3, 0.0)],
        angular=[0.0, 0.5],
        pose_seq=[4, -1],
        pose_stamp_ns=[3, 0],
        map_revision=["abc", None],
        frame=["world", "body"],
        chart=[None, 2],
    ),
    S.CollisionEvent(robot_id="r1", ws_id="w1", stamp_ns=7, position=(1, 1), clearance=-0.01),
    S.SpawnRequest(robot_id="r2", ws_id="w1", position=(0.3, 0.3)),
    S.Movers(
        ws_id="w1",
        stamp_ns=7,
        movers=[S.MoverDisk(mover_id="person1", position=(1, 2), radius=0.3, velocity=(1.2, 0))],
    ),
    S.SimControl(action="reset", robot_id="r2"),
    S.ServiceHealth(service="transform", zid="abc", stamp_ns=8, state="ok", uptime_s=1.0),
    S.AtlasIndex(
        ws_id="w1",
        revision="r2",
        definition_hash="h",
        stamp_ns=9,
        margin=0.1,
        tol=1e-8,
        cells=[
            S.AtlasCell(
                index=0,
                chart_ws_id="w1~c0",
                chart_revision="c0",
                outer=[(0, 0), (1, 0), (1, 1), (0, 1)],
                cut=[[(1, 0), (1, 1)]],
                tile=(0, 0, 1, 1),
            )
        ],
        decomposition={"tile": 1.0},
    ),
    S.MapQuery(
        stamp_ns=10,
        routes=[S.RouteHint(robot_id="r1", start=(0.1, 0.2), goal=(0.5, -0.5))],
    ),
]


def test_every_model_has_a_sample_and_a_unique_type() -> None:
    assert {type(m) for m in SAMPLES} == set(S.MESSAGE_MODELS)
    assert len(S.MODELS_BY_TYPE) == len(S.MESSAGE_MODELS)
    for model in S.MESSAGE_MODELS:
        assert f"confnav.{model.__name__}" == model.TYPE
        assert S.schema_name(model) == model.TYPE


@pytest.mark.parametrize("msg", SAMPLES, ids=lambda m: type(m).__name__)
def test_roundtrip_and_payload_validates_against_exported_schema(msg: S.Message) -> None:
    data = S.encode(msg)
    back = S.decode(type(msg), data)
    assert back == msg
    payload = json.loads(data)
    assert payload["type"] == type(msg).TYPE and payload["schema_version"] == S.SCHEMA_VERSION
    jsonschema.validate(payload, S.json_schema(type(msg)))


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (b"{not json", "invalid_json"),
        (b'{"robot_id":"r1","stamp_ns":1,"x":NaN,"y":0}', "nan_input"),
        (b'{"robot_id":"r1","stamp_ns":1,"x":Infinity,"y":0}', "nan_input"),
        (b'{"schema_version":2,"robot_id":"r1","stamp_ns":1,"x":1,"y":0}', "schema_version"),
        (b'{"type":"confnav.Goal","robot_id":"r1","stamp_ns":1,"x":1,"y":0}', "schema_version"),
        (b'{"robot_id":"r1","stamp_ns":1,"x":1,"y":0,"z":0}', "invalid_input"),
        (b'{"robot_id":"r1","stamp_ns":"1","x":1,"y":0}', "invalid_input"),
        (b'{"robot_id":"r/1","stamp_ns":1,"x":1,"y":0}', "invalid_input"),
        (b'{"robot_id":"r1","stamp_ns":-1,"x":1,"y":0}', "invalid_input"),
        (b"[]", "invalid_input"),
    ],
)
def test_decode_rejects_with_a_reason(payload: bytes, reason: str) -> None:
    with pytest.raises(S.DecodeError) as err:
        S.decode(S.Pose, payload)
    assert err.value.reason == reason


def test_size_limit_checked_before_parsing() -> None:
    big = b'{"robot_id":"r1","stamp_ns":1,"x":1,"y":0,"pad":"' + b"x" * 70_000 + b'"}'
    with pytest.raises(S.DecodeError) as err:
        S.decode(S.Pose, big)
    assert err.value.reason == "too_large"
    assert S.max_bytes(S.TransformSolution) > S.max_bytes(S.Pose)


def test_models_are_strict_and_frozen() -> None:
    with pytest.raises(ValueError):
        S.Goal(robot_id="r1", ws_id="w", goal=(0, 0), v_max=0.0)
    with pytest.raises(ValueError):
        S.Goal(robot_id="r1", ws_id="w", goal=(0, 0), navfn="potential")  # type: ignore[arg-type]
    with pytest.raises(ValueError):
        S.WorkspaceDefinition(ws_id="w", outer=[(0, 0), (1, 0)])  # fewer than 3 vertices
    p = S.Pose(robot_id="r1", stamp_ns=1, x=0, y=0)
    with pytest.raises(ValueError):
        p.x = 2.0  # type: ignore[misc]


def test_export_writes_every_schema(tmp_path: Path) -> None:
    paths = S.export_schemas(tmp_path)
    assert sorted(p.name for p in paths) == sorted(
        f"{m.TYPE}.schema.json" for m in S.MESSAGE_MODELS
    )
    for model in S.MESSAGE_MODELS:
        data = (tmp_path / f"{model.TYPE}.schema.json").read_bytes()
        assert data == S.schema_bytes(model)
        schema = json.loads(data)
        jsonschema.Draft202012Validator.check_schema(schema)
        assert schema["$id"] == model.TYPE
        # the wire contract is what decode accepts: type and schema_version may be omitted,
        # but when present they must name this model and version
        required = schema.get("required", [])  # MapQuery: every field optional
        assert "type" not in required and "schema_version" not in required
        assert schema["properties"]["type"]["const"] == model.TYPE
        assert schema["properties"]["schema_version"]["const"] == S.SCHEMA_VERSION
        assert schema["additionalProperties"] is False


def test_cli_schemas_export(tmp_path: Path) -> None:
    from confnav.cli.app import main

    assert main(["schemas", "export", str(tmp_path / "s")]) == 0
    assert len(list((tmp_path / "s").glob("confnav.*.schema.json"))) == len(S.MESSAGE_MODELS)


@pytest.mark.parametrize("bad", ["", "a*", "a$b", "a#", "a?", "a/b", "a b", "a\tb", "@x", "x" * 65])
def test_invalid_ids(bad: str) -> None:
    assert not is_valid_id(bad)
    with pytest.raises(KeyError_):
        validate_id(bad)
    with pytest.raises(KeyError_):
        Keys().robot(bad, "pose")


def test_keys_build_and_parse() -> None:
    k = Keys("fleet/a")
    key = k.robot("r-1.x", "cmd_vel")
    assert key == "fleet/a/robot/r-1.x/cmd_vel"
    p = k.parse(key)
    assert (p.group, p.ident, p.kind) == ("robot", "r-1.x", "cmd_vel")
    assert k.parse(k.ws("w", "transform")).kind == "transform"
    assert k.parse(k.health("transform", "abc")).group == "health"
    for bad in [
        "confnav/robot/r1/pose",
        "fleet/a/robot/r1/odom",
        "fleet/a/robot/r1",
        "fleet/a/x/r/y",
    ]:
        with pytest.raises(KeyError_):
            k.parse(bad)
    assert S.model_for_key_parts("robot", "pose") is S.Pose
    assert S.model_for_key_parts("health", "zid") is S.ServiceHealth
    assert S.model_for_key_parts("robot", "odom") is None


def _accepts(model: type[S.Message], payload: dict[str, object]) -> tuple[bool, bool]:
    """(validates against the exported JSON Schema, decodes)."""
    valid = jsonschema.Draft202012Validator(S.json_schema(model)).is_valid(payload)
    try:
        S.decode(model, json.dumps(payload).encode())
        decodes = True
    except S.DecodeError:
        decodes = False
    return valid, decodes


def _variants(msg: S.Message) -> list[tuple[str, dict[str, object]]]:
    """The full payload, each field left out in turn, every optional field left out, an unknown
    field, a wrong type tag, a wrong version, a wrong-typed value of each field."""
    full = json.loads(S.encode(msg))
    required = set(S.json_schema(type(msg)).get("required", []))
    out: list[tuple[str, dict[str, object]]] = [("full", full)]
    out.append(("minimal", {k: v for k, v in full.items() if k in required}))
    for k in full:
        out.append((f"without {k}", {j: v for j, v in full.items() if j != k}))
        out.append((f"{k} as object", {**full, k: {"x": 1}}))
    out.append(("extra field", {**full, "extra": 1}))
    out.append(("other type", {**full, "type": "confnav.Other"}))
    out.append(("version 2", {**full, "schema_version": 2}))
    return out


@pytest.mark.parametrize("msg", SAMPLES, ids=lambda m: type(m).__name__)
def test_json_schema_accepts_exactly_what_decode_accepts(msg: S.Message) -> None:
    """For every model: a payload that validates against the exported schema decodes, and one
    that decodes validates; over accepted and rejected variants of a real message."""
    model = type(msg)
    seen = set()
    for what, payload in _variants(msg):
        valid, decodes = _accepts(model, payload)
        assert valid == decodes, (model.TYPE, what, valid, decodes)
        seen.add(valid)
    assert seen == {True, False}  # both sides of the contract were exercised
    # in particular type and schema_version may be left out, as the services accept
    full = json.loads(S.encode(msg))
    bare = {k: v for k, v in full.items() if k not in ("type", "schema_version")}
    assert _accepts(model, bare) == (True, True)
