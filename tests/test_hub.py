"""The standalone hub for multi-host runs (``python -m messages.hub``), over TLS on loopback.

The nodes are started the documented way: each with its own generated configuration file
(``--zenoh-config``), as they would be on other machines.
"""

from __future__ import annotations

import contextlib
import shutil
import signal
import socket
import subprocess
import time

import pytest
import zenoh

from messages.recording import metadata, read_messages
from tests.conftest import finish, free_endpoint, spawn

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs openssl for test certificates")


@pytest.fixture(scope="module")
def certificates(tmp_path_factory):
    """A throw-away CA and a hub certificate for localhost / 127.0.0.1."""
    d = tmp_path_factory.mktemp("tls")

    def ssl(*args):
        subprocess.run(["openssl", *args], cwd=d, check=True, capture_output=True)

    ssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca-key.pem", "-out", "ca.pem", "-days", "1",
        "-subj", "/CN=meltloop-test-ca")
    ssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", "hub-key.pem", "-out", "hub.csr", "-subj", "/CN=localhost")
    (d / "ext.cnf").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    ssl("x509", "-req", "-in", "hub.csr", "-CA", "ca.pem", "-CAkey", "ca-key.pem", "-CAcreateserial", "-out", "hub.pem",
        "-days", "1", "-extfile", "ext.cnf")
    return d


def start_hub(tmp_path, certificates, run_id):
    port = free_endpoint().rsplit(":", 1)[1]
    endpoint = f"tls/localhost:{port}"
    out_dir = tmp_path / "hub"
    hub = spawn("messages.hub", "--run-id", run_id, "--listen", endpoint, "--out-dir", str(out_dir),
                "--node", "recorder", "--node", "controller", "--node", "plant",
                "--tls-ca", str(certificates / "ca.pem"), "--tls-cert", str(certificates / "hub.pem"),
                "--tls-key", str(certificates / "hub-key.pem"))
    deadline = time.monotonic() + 20
    while not (out_dir / "plant.json5").exists() and time.monotonic() < deadline:
        assert hub.poll() is None, finish(hub)[1]
        time.sleep(0.05)
    time.sleep(0.3)  # the router opens its listener after writing the files
    return hub, out_dir


def test_a_run_across_hosts_through_the_tls_hub(tmp_path, certificates, run_id):
    hub, cfg = start_hub(tmp_path, certificates, run_id)
    out = tmp_path / "run.mcap"
    common = ("--run-id", run_id)
    try:
        assert oct((cfg / "plant.json5").stat().st_mode & 0o777) == "0o600"
        recorder = spawn("messages.recorder", "--out", str(out), "--expect", "plant", "--expect", "controller",
                         "--zenoh-config", str(cfg / "recorder.json5"), *common)
        controller = spawn("controller_node", "--controller", "pid", "--setpoint-mm2", "0.063",
                           "--require", "recorder", "--zenoh-config", str(cfg / "controller.json5"), *common)
        camera = spawn("fe_node.example_sensor", "--rate-hz", "200", "--max-steps", "100",
                       "--require", "recorder", "--require", "controller",
                       "--zenoh-config", str(cfg / "plant.json5"), *common)
        results = {name: finish(p, timeout=90) for name, p in
                   (("camera", camera), ("controller", controller), ("recorder", recorder))}
    finally:
        hub.send_signal(signal.SIGINT)
        hub_status, hub_out = finish(hub)
    for name, (status, output) in results.items():
        assert status == 0, f"{name}: {output}"
        assert "unauthenticated" not in output
    assert hub_status == 0, hub_out
    assert not (cfg / "plant.json5").exists()  # the passwords die with the hub
    assert len(list(read_messages(out, "/plant/state"))) == 101
    assert metadata(out)["meltloop.counts"]["complete"] == "true"


def test_the_tls_hub_refuses_wrong_credentials(tmp_path, certificates, run_id):
    hub, cfg = start_hub(tmp_path, certificates, run_id)
    try:
        good = zenoh.Config.from_file(str(cfg / "controller.json5"))
        with zenoh.open(good) as session:
            assert list(session.info.routers_zid())
        wrong = zenoh.Config.from_file(str(cfg / "controller.json5"))
        wrong.insert_json5("transport/auth/usrpwd", '{"user": "controller", "password": "guess"}')
        with pytest.raises(zenoh.ZError):
            zenoh.open(wrong)
    finally:
        hub.send_signal(signal.SIGINT)
        assert finish(hub)[0] == 0


def hub_main(*args: str) -> int:
    from messages.hub import main

    return main(["--run-id", "r1", "--node", "plant", "--node", "controller", *args])


@contextlib.contextmanager
def taken_endpoint():
    """A loopback endpoint whose port another socket holds: a hub cannot listen there."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        yield f"tcp/127.0.0.1:{taken.getsockname()[1]}"


def test_a_listen_other_machines_can_reach_needs_tls(tmp_path, capsys):
    for endpoint in ("tcp/0.0.0.0:7447", "tcp/192.0.2.1:7447", "tcp/hub.example:7447"):
        assert hub_main("--listen", endpoint, "--out-dir", str(tmp_path / "hub")) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"--listen {endpoint}: other machines can reach it, so it needs TLS" in err[0]
        assert not (tmp_path / "hub").exists()


def test_an_existing_out_dir_is_refused(tmp_path, capsys):
    out_dir = tmp_path / "hub"
    out_dir.mkdir(mode=0o777)
    out_dir.chmod(0o777)
    with taken_endpoint() as endpoint:
        assert hub_main("--listen", endpoint, "--out-dir", str(out_dir)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--out-dir {out_dir}: exists; give a new folder" in err[0]
    assert list(out_dir.iterdir()) == []


def test_a_hub_that_cannot_listen_leaves_no_credentials(tmp_path, capsys, monkeypatch):
    """The port is taken: exit status 1, and neither the node configurations (with their passwords)
    nor the credentials folder stay behind."""
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    out_dir = tmp_path / "hub"
    with taken_endpoint() as endpoint:
        assert hub_main("--listen", endpoint, "--out-dir", str(out_dir)) == 1
    assert "cannot listen on" in capsys.readouterr().err
    assert not out_dir.exists()
    assert list((tmp_path / "tmp").iterdir()) == []
