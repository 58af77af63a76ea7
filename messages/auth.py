"""Per-run credentials and access control: who may publish and read what in one run.

``launch.py`` makes fresh credentials for every run (:class:`RunCredentials`): one user per node
(the node's name) with a random password, a dictionary file readable only by the current user,
and a zenoh **router** configuration for the run's hub that

- accepts only sessions that authenticate with one of these users (zenoh ``usrpwd``; a process
  without them cannot open a link), and
- lets each node publish only its own keys (zenoh access control, checked on what the hub
  receives): ``plant`` the ``plant/*`` topics, ``controller`` the ``controller/*`` topics,
  every node only its own run events, log and liveliness token;
- lets each node read only what its roles need (checked on what the hub sends, :data:`READS`):
  the plant the commands, the controller the plant state and the run events, the recorder and
  the live view everything; every node sees the liveliness tokens (readiness and presence);
- serves no queries: no node may declare a queryable.

Nodes get their user and password from the environment (:data:`USER_ENV`, :data:`PASSWORD_ENV`),
never from argv, and then run as zenoh clients of the hub (:func:`messages.bus.zenoh_config`).
A node started by hand without them runs unauthenticated in peer mode and says so once.
"""

from __future__ import annotations

import json
import os
import secrets
import shutil
import stat
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

from messages.topics import (
    LASER_COMMAND,
    PLANT_STATE,
    PREFIX,
    RUN_EVENTS,
    TOPICS,
    Topic,
    key_expr,
    liveliness_key,
    run_prefix,
)

FOLDER_PREFIX = "meltloop-auth-"
"""A run's credentials live in ``<temp dir>/meltloop-auth-<pid>-<random>``, ``pid`` the process
that made them (so that a later run can remove those of a run that was killed)."""
USER_ENV = "MELTLOOP_ZENOH_USER"
PASSWORD_ENV = "MELTLOOP_ZENOH_PASSWORD"
ROLES = ("plant", "controller", "recorder", "live")
"""Roles: a node of role ``plant`` may publish the ``plant/...`` topics, and so on (``recorder``
and ``live`` publish none); what each role reads is :data:`READS`. A node's role is its name if
that is a role, unless its spec names others (e.g. a camera node ``camera`` with role ``plant``);
a node without a role publishes only its own events and log and reads no topic."""
READS: dict[str, tuple[Topic, ...]] = {
    "plant": (LASER_COMMAND,),
    "controller": (PLANT_STATE, RUN_EVENTS),
    "recorder": tuple(TOPICS.values()),
    "live": tuple(TOPICS.values()),
}
"""The topics a node of each role receives (subscribes to) besides the liveliness tokens."""


def node_credentials() -> tuple[str, str] | None:
    """This process's (user, password) from the environment, or ``None`` if unauthenticated."""
    user, password = os.environ.get(USER_ENV), os.environ.get(PASSWORD_ENV)
    return (user, password) if user and password else None


def publish_keys(run_id: str, node: str, roles: tuple[str, ...]) -> list[str]:
    """Key expressions ``node`` with ``roles`` may publish (put) in run ``run_id``."""
    keys = [f"{PREFIX}/{run_id}/{t.suffix}/{node}" for t in TOPICS.values() if t.per_node]
    keys += [f"{PREFIX}/{run_id}/{t.suffix}" for t in TOPICS.values() if t.suffix.split("/")[0] in roles]
    return keys


def read_keys(run_id: str, roles: tuple[str, ...]) -> list[str]:
    """Key expressions a node with ``roles`` may subscribe to and receive in run ``run_id`` (:data:`READS`)."""
    topics = {t.suffix: t for role in roles for t in READS[role]}
    if len(topics) == len(TOPICS):
        return [run_prefix(run_id)]
    return [key_expr(run_id, t) for t in topics.values()]


def access_control(run_id: str, roles: dict[str, tuple[str, ...]]) -> dict:
    """The hub's zenoh ``access_control`` section for a run with these nodes.

    Default deny. Every authenticated node may watch and query the run's liveliness tokens and
    learn of the subscribers (so that its publishers send); it may subscribe to and receive only
    :func:`read_keys`, put only :func:`publish_keys` and declare only its own liveliness token.
    No queryable, query or reply passes. ``roles`` maps each node name (its zenoh user) to its roles.
    """
    nodes = list(roles)
    alive = [liveliness_key(run_id)]
    rules = [
        {"id": "liveliness", "permission": "allow", "flows": ["ingress"],
         "messages": ["declare_liveliness_subscriber", "liveliness_query"], "key_exprs": alive},
        {"id": "presence", "permission": "allow", "flows": ["egress"], "messages": ["liveliness_token"],
         "key_exprs": alive},
        {"id": "subscribers", "permission": "allow", "flows": ["egress"], "messages": ["declare_subscriber"],
         "key_exprs": [run_prefix(run_id)]},
    ]
    subjects = [{"id": "nodes", "usernames": list(nodes)}]
    policies = [{"rules": ["liveliness", "presence", "subscribers"], "subjects": ["nodes"]}]
    for node in nodes:
        rules += [
            {"id": f"put-{node}", "permission": "allow", "flows": ["ingress"], "messages": ["put"],
             "key_exprs": publish_keys(run_id, node, roles[node])},
            {"id": f"alive-{node}", "permission": "allow", "flows": ["ingress"], "messages": ["liveliness_token"],
             "key_exprs": [liveliness_key(run_id, node)]},
        ]
        own = [f"put-{node}", f"alive-{node}"]
        if reads := read_keys(run_id, roles[node]):
            rules += [
                {"id": f"subscribe-{node}", "permission": "allow", "flows": ["ingress"],
                 "messages": ["declare_subscriber"], "key_exprs": reads},
                {"id": f"receive-{node}", "permission": "allow", "flows": ["egress"], "messages": ["put"],
                 "key_exprs": reads},
            ]
            own += [f"subscribe-{node}", f"receive-{node}"]
        subjects.append({"id": f"user-{node}", "usernames": [node]})
        policies.append({"rules": own, "subjects": [f"user-{node}"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def remove_stale_credentials(temp_dir: Path | None = None) -> list[Path]:
    """Remove this user's credential folders (:data:`FOLDER_PREFIX`) whose making process is gone,
    e.g. after a SIGKILL of ``launch.py`` or the hub; returns them. ``temp_dir``: default the
    system's temporary folder."""
    removed = []
    for folder in Path(temp_dir or tempfile.gettempdir()).glob(f"{FOLDER_PREFIX}*-*"):
        pid = folder.name[len(FOLDER_PREFIX):].partition("-")[0]
        try:
            info = folder.lstat()
        except OSError:
            continue
        if (pid.isdigit() and stat.S_ISDIR(info.st_mode) and info.st_uid == os.getuid()
                and not _running(int(pid))):
            shutil.rmtree(folder, ignore_errors=True)
            removed.append(folder)
    return removed


@dataclass
class RunCredentials:
    """Fresh credentials of one run: a random password per node, kept in a private folder.

    Use as a context manager; the folder (dictionary file) is removed on exit, and on entry the
    folders of earlier runs whose process is gone (:func:`remove_stale_credentials`).

    Attributes
    ----------
    run_id : str
        The run the access control is written for.
    roles : dict of str to tuple of str
        Node name (each is a zenoh user) -> its roles.
    """

    run_id: str
    roles: dict[str, tuple[str, ...]]
    passwords: dict[str, str] = field(default_factory=dict)
    folder: Path | None = None

    def __enter__(self) -> RunCredentials:
        remove_stale_credentials()
        self.folder = Path(tempfile.mkdtemp(prefix=f"{FOLDER_PREFIX}{os.getpid()}-"))  # mode 0700
        self.passwords = {node: secrets.token_urlsafe(24) for node in self.roles}
        self.dictionary_file.touch(mode=0o600)
        self.dictionary_file.write_text("".join(f"{n}:{p}\n" for n, p in self.passwords.items()))
        return self

    def __exit__(self, *_: object) -> None:
        if self.folder is not None:
            shutil.rmtree(self.folder, ignore_errors=True)

    @property
    def dictionary_file(self) -> Path:
        """The ``user:password`` lines the hub checks links against (mode 0600)."""
        assert self.folder is not None, "use RunCredentials as a context manager"
        return self.folder / "credentials.txt"

    def env(self, node: str) -> dict[str, str]:
        """Environment variables that give ``node`` its identity."""
        return {USER_ENV: node, PASSWORD_ENV: self.passwords[node]}

    def hub_settings(self) -> dict[str, str]:
        """zenoh configuration entries (path -> JSON5 value) of the run's authenticating hub."""
        return {
            "transport/auth/usrpwd": json.dumps({"dictionary_file": str(self.dictionary_file)}),
            "access_control": json.dumps(access_control(self.run_id, self.roles)),
        }
