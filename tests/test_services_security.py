"""Security end to end on loopback: the TLS + access-control sample router
(``deploy/multi-machine/router-tls.json5``, only its endpoints and certificate paths replaced)
with a CA and certificates generated at test time. A client whose certificate names no policy
can neither publish commands or definitions nor read poses; a robot certificate may publish
only its own pose and receive only its own command; a certificate of another CA is refused;
the services' loopback TCP listener is the fleet's."""

from __future__ import annotations

import datetime
import ipaddress
import json
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from confnav.schemas import Pose, VelocityCommand, encode
from confnav.services.bus import zenoh_config
from conftest import REPO, wait_for
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import NameOID

SAMPLE = REPO / "deploy" / "multi-machine"


def _name(cn: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def _cert(
    cn: str, key: ec.EllipticCurvePrivateKey, issuer: x509.Name, signer: Any, ca: bool
) -> x509.Certificate:
    now = datetime.datetime.now(datetime.UTC)
    b = (
        x509.CertificateBuilder()
        .subject_name(_name(cn))
        .issuer_name(issuer)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - datetime.timedelta(hours=1))
        .not_valid_after(now + datetime.timedelta(days=1))
        .add_extension(x509.BasicConstraints(ca=ca, path_length=None), critical=True)
    )
    if not ca:
        san = [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]
        b = b.add_extension(x509.SubjectAlternativeName(san), critical=False)
    return b.sign(signer, hashes.SHA256())


def _write(d: Path, stem: str, key: ec.EllipticCurvePrivateKey, cert: x509.Certificate) -> None:
    (d / f"{stem}-key.pem").write_bytes(
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        )
    )
    (d / f"{stem}-cert.pem").write_bytes(cert.public_bytes(serialization.Encoding.PEM))


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """ca.pem; router, robot-r1 and visitor certificates of that CA; a robot-r1 certificate
    of another CA (rogue)."""
    d = tmp_path_factory.mktemp("pki")
    cas = {}
    for ca_name in ("confnav-ca", "rogue-ca"):
        key = ec.generate_private_key(ec.SECP256R1())
        cas[ca_name] = (key, _cert(ca_name, key, _name(ca_name), key, ca=True))
    (d / "ca.pem").write_bytes(cas["confnav-ca"][1].public_bytes(serialization.Encoding.PEM))
    for stem, cn, ca_name in (
        ("router", "confnav-router", "confnav-ca"),
        ("robot", "robot-r1", "confnav-ca"),
        ("visitor", "visitor", "confnav-ca"),
        ("rogue", "robot-r1", "rogue-ca"),
    ):
        ca_key, ca_cert = cas[ca_name]
        key = ec.generate_private_key(ec.SECP256R1())
        _write(d, stem, key, _cert(cn, key, ca_cert.subject, ca_key, ca=False))
    return d


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _set(conf: zenoh.Config, key: str, value: Any) -> None:
    conf.insert_json5(key, json.dumps(value))


@pytest.fixture
def router(pki: Path) -> Iterator[tuple[str, str]]:
    """The sample router on loopback; yields (tls endpoint, tcp endpoint)."""
    tls, tcp = f"tls/127.0.0.1:{_free_port()}", f"tcp/127.0.0.1:{_free_port()}"
    conf = zenoh.Config.from_file(str(SAMPLE / "router-tls.json5"))
    _set(conf, "listen/endpoints", [tls, tcp])
    _set(conf, "connect/endpoints", [])
    for field, name in (
        ("root_ca_certificate", "ca.pem"),
        ("listen_private_key", "router-key.pem"),
        ("listen_certificate", "router-cert.pem"),
        ("connect_private_key", "router-key.pem"),
        ("connect_certificate", "router-cert.pem"),
    ):
        _set(conf, f"transport/link/tls/{field}", str(pki / name))
    with zenoh.open(conf):
        yield tls, tcp


def _tls_client(pki: Path, endpoint: str, stem: str) -> zenoh.Session:
    """A robot-side session from the sample client config, with certificate ``stem``."""
    conf = zenoh.Config.from_file(str(SAMPLE / "robot-client-tls.json5"))
    _set(conf, "connect/endpoints", [endpoint])
    _set(conf, "transport/link/tls/root_ca_certificate", str(pki / "ca.pem"))
    _set(conf, "transport/link/tls/connect_private_key", str(pki / f"{stem}-key.pem"))
    _set(conf, "transport/link/tls/connect_certificate", str(pki / f"{stem}-cert.pem"))
    return zenoh.open(conf)


class Inbox:
    """Samples received by subscribers of one session, per subscribed key expression."""

    def __init__(self, session: zenoh.Session) -> None:
        self.session = session
        self.got: dict[str, list[tuple[str, bytes]]] = {}
        self._lock = threading.Lock()
        self._subs: list[Any] = []

    def listen(self, keyexpr: str) -> list[tuple[str, bytes]]:
        box: list[tuple[str, bytes]] = []
        self.got[keyexpr] = box

        def on(sample: zenoh.Sample) -> None:
            with self._lock:
                box.append((str(sample.key_expr), sample.payload.to_bytes()))

        self._subs.append(self.session.declare_subscriber(keyexpr, on))
        return box


def _cmd(rid: str) -> bytes:
    return encode(VelocityCommand(robot_id=rid, stamp_ns=time.time_ns(), linear=(1.0, 0.0)))


def _pose(rid: str, seq: int = 0) -> bytes:
    return encode(Pose(robot_id=rid, stamp_ns=time.time_ns(), seq=seq, x=0.0, y=0.0))


@pytest.mark.integration
@pytest.mark.timeout(60)
def test_tls_access_control_end_to_end(pki: Path, router: tuple[str, str]) -> None:
    tls, tcp = router
    local = zenoh.open(zenoh_config("client", connect=[tcp]))  # the services' side
    robot = _tls_client(pki, tls, "robot")
    visitor = _tls_client(pki, tls, "visitor")
    # separate sessions for the attempts (a session delivers its own puts to its own
    # subscribers without the router: that is not what is checked here)
    robot_b, visitor_b = _tls_client(pki, tls, "robot"), _tls_client(pki, tls, "visitor")
    sessions = [local, robot, visitor, robot_b, visitor_b]
    try:
        srv = Inbox(local)
        poses = srv.listen("confnav/robot/*/pose")
        cmds = srv.listen("confnav/robot/*/cmd_vel")
        defs = srv.listen("confnav/ws/*/definition")
        bot = Inbox(robot)
        own_cmd = bot.listen("confnav/robot/r1/cmd_vel")
        other_cmd = bot.listen("confnav/robot/r2/cmd_vel")
        any_cmd = bot.listen("confnav/robot/*/cmd_vel")  # a superset of its key: denied
        bot_poses = bot.listen("confnav/robot/*/pose")
        spy = Inbox(visitor)
        spied = [spy.listen(k) for k in ("confnav/robot/r1/pose", "confnav/**")]
        time.sleep(0.5)  # declarations propagate

        # positive controls (repeated until the declarations have propagated): the robot's
        # pose reaches the services, the services' command for r1 reaches the robot
        wait_for(lambda: robot.put("confnav/robot/r1/pose", _pose("r1")) or poses, 10, 0.2)
        wait_for(lambda: local.put("confnav/robot/r1/cmd_vel", _cmd("r1")) or own_cmd, 10, 0.2)
        time.sleep(0.3)
        n_poses, n_cmds, n_own = len(poses), len(cmds), len(own_cmd)

        # what must not pass
        visitor_b.put("confnav/robot/r1/cmd_vel", _cmd("r1"))  # drive someone's robot
        visitor_b.put("confnav/robot/*/cmd_vel", _cmd("r1"))  # drive every robot
        visitor_b.put("confnav/ws/default/definition", b'{"ws_id":"default"}')
        visitor_b.put("confnav/robot/r1/pose", _pose("r1", 99))  # spoof a pose
        robot_b.put("confnav/robot/r2/pose", _pose("r2"))  # a robot spoofing another
        robot_b.put("confnav/robot/r1/cmd_vel", _cmd("r1"))  # ... or commanding
        robot_b.put("confnav/robot/*/cmd_vel", _cmd("r2"))
        robot_b.put("confnav/ws/default/definition", b'{"ws_id":"default"}')
        local.put("confnav/robot/r2/cmd_vel", _cmd("r2"))  # another robot's command
        for i in range(1, 4):  # the services' traffic the visitor must not read
            robot.put("confnav/robot/r1/pose", _pose("r1", i))
            local.put("confnav/robot/r1/cmd_vel", _cmd("r1"))
        wait_for(lambda: len(poses) == n_poses + 3 and len(own_cmd) == n_own + 3, timeout=10)
        time.sleep(0.5)  # anything denied would have arrived by now

        assert {k for k, _ in poses} == {"confnav/robot/r1/pose"}
        assert [json.loads(p)["seq"] for _k, p in poses[n_poses:]] == [1, 2, 3]  # no 99
        assert [k for k, _ in cmds[n_cmds:]] == [
            "confnav/robot/r2/cmd_vel",
            *["confnav/robot/r1/cmd_vel"] * 3,
        ]  # only the services' own commands
        assert defs == []
        assert {k for k, _ in own_cmd} == {"confnav/robot/r1/cmd_vel"}
        # its wildcard subscription sees only what the router delivers to the session anyway
        # (and the pose subscription only its own puts, delivered inside the session)
        assert other_cmd == []
        assert [json.loads(p)["seq"] for _k, p in bot_poses] == [
            json.loads(p)["seq"] for _k, p in poses
        ]
        assert {k for k, _ in any_cmd} <= {"confnav/robot/r1/cmd_vel"}
        assert spied == [[], []]
    finally:
        for s in reversed(sessions):
            s.close()  # type: ignore[no-untyped-call]


@pytest.mark.integration
@pytest.mark.timeout(60)
def test_certificate_of_another_ca_is_refused(pki: Path, router: tuple[str, str]) -> None:
    tls, tcp = router
    with zenoh.open(zenoh_config("client", connect=[tcp])) as local:
        got: list[bytes] = []
        sub = local.declare_subscriber(
            "confnav/robot/*/pose", lambda s: got.append(s.payload.to_bytes())
        )
        try:
            rogue = _tls_client(pki, tls, "rogue")
        except zenoh.ZError as exc:  # the TLS handshake fails: no session at all
            assert "tls" in str(exc).lower() or "connect" in str(exc).lower() or str(exc)
        else:  # a session without a link: nothing it puts arrives
            rogue.put("confnav/robot/r1/pose", _pose("r1"))
            time.sleep(1.0)
            rogue.close()  # type: ignore[no-untyped-call]
            assert got == []
        sub.undeclare()  # type: ignore[no-untyped-call]
