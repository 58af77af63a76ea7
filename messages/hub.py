"""A run's authenticating hub on its own, for runs whose nodes live on several machines.

``launch.py`` opens this hub itself for a run on one machine. When nodes run on other hosts,
start the hub by hand on a machine-network address; it writes one zenoh configuration per node
(client of the hub, its own user and password, TLS trust if given) and the credentials
dictionary, each readable by the current user only, into ``--out-dir``. Copy each node's file
to its host and start the node with ``--zenoh-config FILE --run-id RUN``:

    python -m messages.hub --run-id R1 --listen tls/192.168.10.5:7447 --out-dir hub-R1 \\
        --node recorder --node controller --node plant --tls-ca ca.pem --tls-cert hub.pem --tls-key hub-key.pem
    python -m fe_node --run-id R1 --zenoh-config hub-R1/plant.json5 --require recorder --require controller

The access control is :func:`messages.auth.access_control` (the same as ``launch.py``'s):
each node publishes only its own keys and reads only what its role needs; ``--node NAME:ROLE``
gives a node another name than its role (e.g. ``camera:plant``). Stop with Ctrl-C.

A ``--listen`` endpoint other machines can reach must be ``tls/`` (a plain one is refused, exit
status 2). ``--out-dir`` must not exist: the hub creates it (mode 0700) and removes the node
configurations and the folder whenever it ends, also when it cannot start.
"""

from __future__ import annotations

import contextlib
import ipaddress
import json
from pathlib import Path

from messages.auth import ROLES, RunCredentials
from messages.bus import SHARED_MEMORY, BusSettings, StopFlag, is_name, zenoh_config
from messages.cli import ArgumentParser, UsageError, exit_error, exit_usage, run_main


def parse_nodes(items: list[str]) -> dict[str, tuple[str, ...]]:
    """``NAME`` or ``NAME:ROLE[+ROLE]`` -> {name: roles} (a name that is a role has that role)."""
    roles: dict[str, tuple[str, ...]] = {}
    for item in items:
        name, _, given = item.partition(":")
        node_roles = tuple(r for r in given.split("+") if r) if given else ((name,) if name in ROLES else ())
        if not is_name(name) or not set(node_roles) <= set(ROLES):
            raise UsageError(f"--node {item!r}: expected NAME or NAME:ROLE with ROLE among {', '.join(ROLES)}")
        roles[name] = node_roles
    if not roles:
        raise UsageError("--node: give at least one node")
    return roles


def is_loopback_host(host: str) -> bool:
    """Whether ``host`` (an address or ``localhost``) is reachable from this machine only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.removeprefix("[").removesuffix("]")).is_loopback
    except ValueError:  # a host name: it may resolve to anything
        return False


def is_loopback(endpoint: str) -> bool:
    """Whether zenoh ``endpoint`` (``proto/host:port``) listens on this machine only."""
    address = endpoint.partition("/")[2].split("?")[0].split("#")[0]
    return is_loopback_host(address.rpartition(":")[0])


def tls_settings(ca: Path, cert: Path | None = None, key: Path | None = None) -> dict:
    """zenoh ``transport/link/tls`` section: trust ``ca``; serve ``cert``/``key`` (the hub)."""
    tls: dict[str, str] = {"root_ca_certificate": str(ca.resolve())}
    if cert is not None and key is not None:
        tls |= {"listen_certificate": str(cert.resolve()), "listen_private_key": str(key.resolve())}
    return tls


def router_config(credentials: RunCredentials, endpoint: str, tls: dict | None = None, low_latency: bool = False):
    """The zenoh configuration of a run's authenticating hub: a router listening on ``endpoint``
    that checks every link against ``credentials`` and applies the run's access control
    (``low_latency``: on zenoh's low-latency transport, :mod:`messages.bus`)."""
    config = zenoh_config(BusSettings(run_id=credentials.run_id, connect=(), listen=(endpoint,),
                                      low_latency=low_latency))
    config.insert_json5("mode", '"router"')
    # a router waits scouting/delay (500 ms) for peers found by scouting before zenoh.open returns;
    # multicast scouting is off and every node connects to the hub, so there is nothing to wait for
    config.insert_json5("scouting/delay", "0")
    for path, value in credentials.hub_settings().items():
        config.insert_json5(path, value)
    if tls is not None:
        config.insert_json5("transport/link/tls", json.dumps(tls))
    return config


def write_node_configs(credentials: RunCredentials, endpoint: str, out_dir: Path, ca: Path | None) -> list[Path]:
    """One client configuration per node (mode 0600); returns their paths."""
    paths = []
    for node, password in credentials.passwords.items():
        config = {
            "mode": "client",
            "connect": {"endpoints": [endpoint]},
            "scouting": {"multicast": {"enabled": False}},
            "transport": {"auth": {"usrpwd": {"user": node, "password": password}},
                          "shared_memory": {"enabled": SHARED_MEMORY}},
        }
        if ca is not None:
            config["transport"]["link"] = {"tls": tls_settings(ca)}
        path = out_dir / f"{node}.json5"
        path.touch(mode=0o600)
        path.write_text(json.dumps(config, indent=2) + "\n")
        paths.append(path)
    return paths


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m messages.hub``."""
    parser = ArgumentParser(prog="python -m messages.hub", description=__doc__.split("\n\n")[0])
    parser.add_argument("--run-id", required=True, help="the run the access control is written for")
    parser.add_argument("--listen", required=True, metavar="ENDPOINT", help="e.g. tls/192.168.10.5:7447")
    parser.add_argument("--node", action="append", default=[], metavar="NAME[:ROLE]", help="a node of the run")
    parser.add_argument("--out-dir", type=Path, required=True, help="folder for the node configurations")
    parser.add_argument("--tls-ca", type=Path, help="CA certificate the nodes trust (tls/ endpoints)")
    parser.add_argument("--tls-cert", type=Path, help="the hub's certificate")
    parser.add_argument("--tls-key", type=Path, help="the hub's private key")
    args = parser.parse_args(argv)
    try:
        roles = parse_nodes(args.node)
        BusSettings(run_id=args.run_id, listen=(args.listen,))
        tls = [args.tls_ca, args.tls_cert, args.tls_key]
        if args.listen.startswith("tls/") != all(tls) or (any(tls) and not all(tls)):
            raise UsageError("--tls-ca, --tls-cert and --tls-key go together, and with a tls/ --listen endpoint")
        if not all(tls) and not is_loopback(args.listen):
            raise UsageError(f"--listen {args.listen}: other machines can reach it, so it needs TLS "
                             "(tls/HOST:PORT with --tls-ca, --tls-cert and --tls-key)")
        for path in filter(None, tls):
            if not path.is_file():
                raise UsageError(f"--tls-*: file not found: {path}")
        try:
            args.out_dir.mkdir(mode=0o700, parents=True)
        except FileExistsError:
            raise UsageError(f"--out-dir {args.out_dir}: exists; give a new folder (the hub creates it, "
                             "mode 0700, and removes it when it ends)") from None
        except OSError as err:
            raise UsageError(f"--out-dir {args.out_dir}: {err.strerror or err}") from None
    except UsageError as err:
        return exit_usage(parser.prog, err)
    return serve(args.run_id, args.listen, roles, args.out_dir, args.tls_ca, args.tls_cert, args.tls_key)


def serve(run_id: str, endpoint: str, roles: dict[str, tuple[str, ...]], out_dir: Path,
          ca: Path | None, cert: Path | None, key: Path | None) -> int:
    """Write the node configurations into the new folder ``out_dir``, then run the hub until
    SIGINT/SIGTERM; the configurations and ``out_dir`` are removed however it ends."""
    import zenoh

    stop = StopFlag()
    try:
        with RunCredentials(run_id, roles) as credentials:
            write_node_configs(credentials, endpoint, out_dir, ca)
            config = router_config(credentials, endpoint, tls_settings(ca, cert, key) if ca is not None else None)
            try:
                session = zenoh.open(config)
            except zenoh.ZError as err:
                return exit_error("python -m messages.hub",
                                  f"cannot listen on {endpoint}: {str(err).split(' at ')[0]}")
            with session:
                print(f"hub of run {run_id} on {endpoint}; node configurations in {out_dir}/ "
                      f"({', '.join(f'{n}.json5' for n in roles)})", flush=True)
                while not stop.wait(0.2):
                    pass
        return 0
    finally:  # the passwords die with the hub
        for node in roles:
            (out_dir / f"{node}.json5").unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            out_dir.rmdir()  # unless something else was put there


if __name__ == "__main__":
    run_main(main)
