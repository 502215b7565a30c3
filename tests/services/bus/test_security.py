"""The run's bus closed to everyone but its own services: real routers with the generated configs,
real sessions of each role, of no role, with a wrong password or a foreign certificate."""

from __future__ import annotations

import argparse
import json
import os
import stat
import time
from pathlib import Path

import pytest

from services.bus import ROLES
from services.bus.options import add_secure_init_arguments
from services.bus.security import SecureFiles, SecurityError, export_role, init_secure, run_secure_init
from services.bus.session import (
    LivelinessWatch,
    TransportConfigError,
    TransportError,
    ZenohSettings,
    declare_alive,
    free_tcp_port,
    open_router,
    open_session,
    query_latest,
    serve_latest,
)
from services.up.launcher import secure_files
from shared.wire.keys import RunKeys

RUN = "sec"
KEYS = RunKeys(RUN)


class Bus:
    """A router on loopback with a run's security folder, and a session per role."""

    def __init__(self, root: Path, tls: bool = False):
        self.files = init_secure(root, RUN, tls=tls)
        port = free_tcp_port()
        self.endpoint = f"tls/localhost:{port}" if tls else f"tcp/127.0.0.1:{port}"
        self.router = open_router([self.endpoint], config_file=str(self.files.router_config))
        self.sessions = {role: self.open(role) for role in ROLES}
        self.got: dict[str, list[bytes]] = {}
        self._subs = []

    def open(self, role: str | None = None, config: Path | None = None):
        config = config or (self.files.config(role) if role else None)
        return open_session(ZenohSettings(connect=(self.endpoint,), config_file=str(config) if config else None),
                            wait_s=2.0)

    def listen(self, role: str, key: str) -> list[bytes]:
        got = self.got.setdefault(f"{role}<-{key}", [])
        self._subs.append(self.sessions[role].declare_subscriber(key, lambda s: got.append(s.payload.to_bytes())))
        return got

    def close(self) -> None:
        for s in self.sessions.values():
            s.close()
        self.router.close()


@pytest.fixture
def bus(tmp_path: Path):
    b = Bus(tmp_path / "secure")
    yield b
    b.close()


def write_secret(path: Path, config: dict) -> None:
    """A client config with a password, private as a service requires."""
    path.write_text(json.dumps(config))
    path.chmod(0o600)


def settle(predicate=lambda: False, timeout_s: float = 1.5) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not predicate():
        time.sleep(0.05)


def test_the_folder_is_private_complete_and_denies_by_default(tmp_path: Path):
    files = init_secure(tmp_path / "secure", RUN, tls=True, hosts=["robot-lab.local"])
    assert files.tls and files.check(RUN, tls=True) is files
    assert stat.S_IMODE(files.root.stat().st_mode) == 0o700, "the folder's names are others' to list"
    for path in files.root.iterdir():
        assert stat.S_IMODE(path.stat().st_mode) == 0o600, path.name
    router = json.loads(files.router_config.read_text())
    acl = router["access_control"]
    assert acl["enabled"] and acl["default_permission"] == "deny"
    assert {s["id"]: s["usernames"] for s in acl["subjects"]} == {r: [f"{RUN}-{r}"] for r in ROLES}
    assert all(s["cert_common_names"] == [s["id"]] for s in acl["subjects"])  # TLS: the certificate names the role
    assert all(k.startswith(f"cogexplore/{RUN}/") for rule in acl["rules"] for k in rule["key_exprs"])
    passwords = {u["password"] for u in json.loads(files.credentials.read_text())["users"].values()}
    assert len(passwords) == len(ROLES) and all(len(p) >= 24 for p in passwords)
    with pytest.raises(SecurityError, match="already holds credentials"):
        init_secure(files.root, RUN)
    with pytest.raises(SecurityError, match="made for run 'sec', not 'other'"):
        files.check("other")
    bundle = export_role(files.root, "actor", tmp_path / "bundle")
    assert sorted(p.name for p in bundle) == ["actor.json5", "actor.key", "actor.pem", "ca.pem"]
    text = "".join(p.read_text() for p in bundle)
    assert all(p not in text for p in passwords - {json.loads(files.credentials.read_text())["users"]["actor"]["password"]})
    plain = init_secure(tmp_path / "plain", RUN)
    with pytest.raises(SecurityError, match="no TLS certificates"):
        plain.check(RUN, tls=True)
    # the command it names makes them (init alone refuses a folder that holds credentials)
    fix = str(pytest.raises(SecurityError, plain.check, RUN, tls=True).value).split("`")[1].split()
    assert fix[:3] == ["cogexplore", "secure", "init"] and "--force" in fix
    assert init_secure(plain.root, RUN, tls=True, force=True).check(RUN, tls=True)


def test_expired_certificates_are_refused_where_the_run_starts(tmp_path: Path):
    # The router refuses every link an expired certificate signs with the silence of a router that is not
    # there, and `secure init --keep` (compose, at every start) kept them: said at the start instead.
    import datetime

    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec

    files = init_secure(tmp_path / "secure", RUN, tls=True)
    assert files.expired_certificate() is None
    later = datetime.datetime.now(datetime.UTC) + datetime.timedelta(days=366)
    assert files.expired_certificate(later)[0] == "ca.pem"
    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(x509.oid.NameOID.COMMON_NAME, "router")])
    yesterday = datetime.datetime.now(datetime.UTC) - datetime.timedelta(days=1)
    old = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
           .serial_number(1).not_valid_before(yesterday - datetime.timedelta(days=365)).not_valid_after(yesterday)
           .sign(key, hashes.SHA256()))
    (files.root / "router.pem").write_bytes(old.public_bytes(serialization.Encoding.PEM))
    with pytest.raises(SecurityError, match=r"router\.pem expired on .* UTC \(certificates last 365 days\): run "
                                            r"`cogexplore secure init .* --force`"):
        files.check(RUN, tls=True)
    with pytest.raises(SecurityError, match="expired"):
        run_secure_init(init_args(files.root, "--keep", "--tls"))


def test_no_credentials_or_a_wrong_password_get_no_session(bus: Bus, tmp_path: Path):
    with pytest.raises(TransportError):
        bus.open()  # no credentials
    wrong = json.loads(bus.files.config("actor").read_text())
    wrong["transport"]["auth"]["usrpwd"]["password"] = "guess"
    write_secret(tmp_path / "wrong.json5", wrong)
    with pytest.raises(TransportError):
        bus.open(config=tmp_path / "wrong.json5")


def test_each_role_does_its_part_and_nothing_more(bus: Bus):
    """Listeners in one set of sessions, senders in another (a session hears its own puts locally)."""
    s = {role: bus.open(role) for role in ROLES}
    transitions = bus.listen("learner", KEYS.all_transitions)
    actor_weights = bus.listen("actor", KEYS.weights)
    evaluator_weights = bus.listen("evaluator", KEYS.weights)
    actor_flow = bus.listen("actor", KEYS.flow)
    evaluator_flow = bus.listen("evaluator", KEYS.flow)  # the learner's pulse
    stats = bus.listen("viewer", KEYS.all_stats())
    settle()
    s["learner"].put(KEYS.weights, b"real")
    s["learner"].put(KEYS.flow, b"credit")
    for role in ("actor", "evaluator", "viewer"):
        s[role].put(KEYS.weights, f"hijack by {role}".encode())  # case 1: only the learner puts weights
        s[role].put(KEYS.flow, f"forged credit by {role}".encode())  # case 6: only the learner gives credit
    s["actor"].put(KEYS.transitions("a1"), b"step")
    for role in ("learner", "evaluator", "viewer"):
        s[role].put(KEYS.transitions("x"), f"fake step by {role}".encode())
    s["learner"].put(KEYS.learner_stats("l"), b"learner stats")
    s["evaluator"].put(KEYS.eval_results("e"), b"eval")
    s["actor"].put(KEYS.episode_stats("a1"), b"episode")
    settle(lambda: len(stats) >= 3 and evaluator_weights and actor_weights and actor_flow and evaluator_flow
           and transitions)
    settle(timeout_s=0.5)  # and a little more, for anything that should not come
    assert evaluator_weights == actor_weights == [b"real"] and actor_flow == evaluator_flow == [b"credit"]
    assert transitions == [b"step"] and sorted(stats) == [b"episode", b"eval", b"learner stats"]
    for session in s.values():
        session.close()


def test_only_the_learner_answers_the_weights_query_and_announces_a_learner(bus: Bus):
    s = bus.sessions
    rogue = serve_latest(s["actor"], KEYS.weights_latest, lambda: b"rogue")  # noqa: F841
    assert query_latest(s["evaluator"], KEYS.weights_latest, timeout_s=1.0) is None
    real = serve_latest(s["learner"], KEYS.weights_latest, lambda: b"real")  # noqa: F841
    settle(timeout_s=0.5)
    for _ in range(3):  # a rogue responder wins no newly started receiver
        assert query_latest(s["evaluator"], KEYS.weights_latest, timeout_s=2.0) == b"real"
    fake = declare_alive(s["actor"], KEYS.alive("learner", "fake"))  # noqa: F841
    token = declare_alive(s["learner"], KEYS.alive("learner", "l"))  # noqa: F841
    actor_token = declare_alive(s["actor"], KEYS.alive("actor", "a1"))  # noqa: F841
    with LivelinessWatch(s["viewer"], KEYS.all_alive()) as watch:
        assert watch.wait(lambda keys: KEYS.alive("learner", "l") in keys and KEYS.alive("actor", "a1") in keys, 3)
        settle(timeout_s=0.5)
        assert KEYS.alive("learner", "fake") not in watch.alive


def test_only_the_learner_answers_the_config_query_and_the_actors_and_the_evaluator_may_ask(bus: Bus):
    rogues = [serve_latest(bus.sessions[role], KEYS.config, lambda: b"rogue")  # noqa: F841
              for role in ("actor", "evaluator", "viewer")]
    asking = {role: bus.open(role) for role in ("actor", "evaluator", "viewer")}
    assert query_latest(asking["actor"], KEYS.config, timeout_s=1.0) is None
    real = serve_latest(bus.sessions["learner"], KEYS.config, lambda: b"run config")  # noqa: F841
    settle(timeout_s=0.5)
    for role in ("actor", "evaluator"):
        assert query_latest(asking[role], KEYS.config, timeout_s=2.0) == b"run config", role
    assert query_latest(asking["viewer"], KEYS.config, timeout_s=1.0) is None  # not a viewer's part
    for session in asking.values():
        session.close()


def test_tls_with_client_certificates(tmp_path: Path):
    bus = Bus(tmp_path / "secure", tls=True)
    try:
        transitions = bus.listen("learner", KEYS.all_transitions)
        settle(timeout_s=0.5)
        bus.sessions["actor"].put(KEYS.transitions("a1"), b"step over TLS")
        settle(lambda: bool(transitions))
        assert transitions == [b"step over TLS"]
        no_cert = json.loads(bus.files.config("actor").read_text())
        for key in ("connect_certificate", "connect_private_key"):
            no_cert["transport"]["link"]["tls"].pop(key)
        no_cert["transport"]["link"]["tls"]["root_ca_certificate"] = str(bus.files.root / "ca.pem")
        write_secret(tmp_path / "no-cert.json5", no_cert)
        with pytest.raises(TransportError):
            bus.open(config=tmp_path / "no-cert.json5")  # the right password is not enough without a certificate
        # the actor's password with the evaluator's certificate: a session, but not the actor's part
        mixed = json.loads(bus.files.config("actor").read_text())
        mixed["transport"]["link"]["tls"].update(
            {"root_ca_certificate": str(bus.files.root / "ca.pem"),
             "connect_certificate": str(bus.files.root / "evaluator.pem"),
             "connect_private_key": str(bus.files.root / "evaluator.key")})
        write_secret(tmp_path / "mixed.json5", mixed)
        impostor = bus.open(config=tmp_path / "mixed.json5")
        impostor.put(KEYS.transitions("a2"), b"impostor")
        settle(timeout_s=1.0)
        assert transitions == [b"step over TLS"]
        impostor.close()
    finally:
        bus.close()


def test_a_secured_service_refuses_to_start_without_its_files_in_one_line(tmp_path: Path, capsys):
    from services.cli import main

    code = main(["up", "--run", "r", "--runs-dir", str(tmp_path), "--listen", "tls/0.0.0.0:0", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and "secure init" in err and "--tls" in err
    assert not (tmp_path / "r").exists(), "a refused start leaves no run folder"
    code = main(["up", "--run", "r", "--runs-dir", str(tmp_path), "--listen", "tcp/0.0.0.0:7447", "--quiet"])
    assert code == 2 and "TLS only" in capsys.readouterr().err


def test_up_with_tls_makes_the_certificates_for_this_machine(tmp_path: Path):
    import argparse
    import socket

    from cryptography import x509

    from services.up.launcher import Launcher
    from services.up.options import add_up_arguments

    parser = argparse.ArgumentParser()
    add_up_arguments(parser)
    launcher = Launcher(parser.parse_args(["--run", "r", "--runs-dir", str(tmp_path), "--listen", "tls/0.0.0.0:7447",
                                           "--tls", "--host", "lab.example", "--quiet"]))
    assert launcher.secure.tls and launcher.endpoint == "tls/localhost:7447"
    cert = x509.load_pem_x509_certificate((launcher.secure.root / "router.pem").read_bytes())
    names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value.get_values_for_type(x509.DNSName)
    assert {"localhost", socket.gethostname(), "lab.example"} <= set(names)


def test_a_folder_an_older_release_made_gets_this_releases_rules_and_keeps_its_passwords(tmp_path: Path, capsys):
    # Folders made before the evaluator's flow-control grant kept the old rules: its evaluator never
    # heard the learner's pulse. `secure init --keep` (compose) and `up` now bring the rules up to date.
    files = init_secure(tmp_path / "secure", RUN)
    credentials = files.credentials.read_text()
    users = files.config("evaluator").read_text()
    for path in (files.router_config, files.root / "router-zenohd.json5"):
        config = json.loads(path.read_text())
        config["access_control"]["rules"] = [r for r in config["access_control"]["rules"]
                                             if not (r["id"].startswith("evaluator") and KEYS.flow in r["key_exprs"])]
        path.write_text(json.dumps(config))
    assert files.outdated_rules(RUN) == [files.router_config, files.root / "router-zenohd.json5"]
    with pytest.raises(SecurityError, match=r"not this release's .* secure init .* --keep"):
        files.check(RUN)
    zenohd_paths = json.loads((files.root / "router-zenohd.json5").read_text())["transport"]
    parser = argparse.ArgumentParser()
    add_secure_init_arguments(parser)
    assert run_secure_init(parser.parse_args([str(files.root), "--run", RUN, "--keep"])) == 0
    capsys.readouterr()
    assert files.outdated_rules(RUN) == [] and files.check(RUN) is files
    assert files.credentials.read_text() == credentials and files.config("evaluator").read_text() == users
    assert json.loads((files.root / "router-zenohd.json5").read_text())["transport"] == zenohd_paths
    assert stat.S_IMODE(files.router_config.stat().st_mode) == 0o600

    # up does the same to its run's folder; then the evaluator hears the pulse on a real router.
    config = json.loads(files.router_config.read_text())
    config["access_control"]["rules"] = config["access_control"]["rules"][:-1]
    files.router_config.write_text(json.dumps(config))
    assert secure_files(files.root, RUN, tls=False).outdated_rules(RUN) == []
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    with open_router([endpoint], config_file=str(files.router_config)):
        learner, evaluator = (open_session(ZenohSettings(connect=(endpoint,), config_file=str(files.config(role))),
                                           wait_s=2.0) for role in ("learner", "evaluator"))
        heard: list[bytes] = []
        sub = evaluator.declare_subscriber(KEYS.flow, lambda s: heard.append(s.payload.to_bytes()))  # noqa: F841
        settle(timeout_s=0.5)
        learner.put(KEYS.flow, b"pulse")
        settle(lambda: heard)
        assert heard == [b"pulse"]
        learner.close()
        evaluator.close()


def init_args(root: Path, *extra: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_secure_init_arguments(parser)
    return parser.parse_args([str(root), "--run", RUN, *extra])


def passwords_in(files) -> set[tuple[str, str]]:  # type: ignore[no-untyped-def]
    """Every (user, password) pair the folder's files name: one per role when they agree."""
    pairs = {(u["user"], u["password"]) for u in json.loads(files.credentials.read_text())["users"].values()}
    pairs |= {tuple(line.split(":", 1)) for line in (files.root / "users.txt").read_text().splitlines()}
    for role in ROLES:
        auth = json.loads(files.config(role).read_text())["transport"]["auth"]["usrpwd"]
        pairs.add((auth["user"], auth["password"]))
    return pairs


@pytest.mark.parametrize("force", [False, True])
def test_a_folder_cut_short_is_made_anew_by_the_next_init_not_kept_half_made(tmp_path: Path, capsys, force: bool):
    # The credentials file, the mark of a complete folder, was written first: a folder cut short (a full
    # disk, a kill) was kept by --keep and `up`, refused as incomplete, and `secure init` refused it too.
    root = tmp_path / "secure"
    if force:  # replacing a complete folder: no mix of its passwords and the new ones is kept
        init_secure(root, RUN).config("actor").unlink()
    (root / "actor.json5").mkdir(parents=True)  # writing it fails, as a full disk would
    with pytest.raises(OSError):
        init_secure(root, RUN, force=force)
    (root / "actor.json5").rmdir()
    assert run_secure_init(init_args(root, "--keep")) == 0
    capsys.readouterr()
    files = SecureFiles(root).check(RUN)
    assert len(passwords_in(files)) == len(ROLES), "one password per role, in every file"


def test_a_file_or_link_left_where_a_secret_is_written_is_replaced_not_written_through(tmp_path: Path):
    root, outside = tmp_path / "secure", tmp_path / "outside.txt"
    root.mkdir()
    outside.write_text("")
    outside.chmod(0o644)
    (root / f".credentials.json.tmp-{os.getpid()}").symlink_to(outside)
    stale = root / f".users.txt.tmp-{os.getpid()}"
    stale.write_text("left by a killed writer\n")
    stale.chmod(0o644)
    files = init_secure(root, RUN)
    assert outside.read_text() == "", "the passwords went where the link pointed"
    for path in files.root.iterdir():
        assert stat.S_IMODE(path.lstat().st_mode) == 0o600 and not path.is_symlink(), path.name


def test_a_secret_other_users_may_read_is_refused_in_one_line_and_a_certificate_is_not(tmp_path: Path, capsys):
    # Like ssh with a private key: a secret copied with a umask of 022 (or chmod 644) gives the run's
    # passwords to every user of the machine; a service used it all the same.
    from services.cli import main

    files = init_secure(tmp_path / "secure", RUN, tls=True)
    bundle = tmp_path / "bundle"
    export_role(files.root, "actor", bundle)
    actor = ZenohSettings(config_file=str(bundle / "actor.json5"))
    router = ZenohSettings(mode="router", config_file=str(files.router_config))
    for public in (bundle / "ca.pem", bundle / "actor.pem", files.root / "router.pem", files.root / "ca.pem"):
        public.chmod(0o644)  # certificates are public: what init and export write, as they are, passes
    files.check(RUN, tls=True)
    actor.to_config()
    router.to_config()
    export_role(files.root, "actor", bundle)
    uses = {files.credentials: lambda: files.check(RUN), bundle / "actor.json5": actor.to_config,
            bundle / "actor.key": actor.to_config, files.root / "users.txt": router.to_config,
            files.root / "router.key": router.to_config, files.root / "actor.key": lambda: export_role(
                files.root, "actor", tmp_path / "again")}
    for secret, use in uses.items():
        for mode in (0o644, 0o640, 0o602):  # others or the group may read it, or others may write it
            secret.chmod(mode)
            with pytest.raises((SecurityError, TransportConfigError)) as refused:
                use()
            assert str(refused.value).startswith(f"{secret} holds secrets"), mode
            assert str(refused.value).endswith(f"run `chmod 600 {secret}`"), mode
        secret.chmod(0o600)
    assert not (tmp_path / "again").exists(), "a refused export writes nothing"
    (bundle / "actor.key").chmod(0o644)
    with pytest.raises(TransportConfigError, match="actor.key holds secrets"):
        # where the settings are made: it was a traceback in an actor's first thread to open a session
        ZenohSettings(config_file=str(bundle / "actor.json5"))
    (files.root / "actor.json5").chmod(0o644)
    code = main(["secure", "export", str(files.root), "--role", "actor", "--out", str(tmp_path / "again")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and f"chmod 600 {files.root / 'actor.json5'}" in err


def test_export_closes_a_folder_of_its_own_and_refuses_one_that_holds_other_files(tmp_path: Path):
    files = init_secure(tmp_path / "secure", RUN)
    bundle = tmp_path / "bundle"
    bundle.mkdir(mode=0o755)
    export_role(files.root, "actor", bundle)
    assert stat.S_IMODE(bundle.stat().st_mode) == 0o700, "the bundle's names are others' to list"
    bundle.chmod(0o755)
    export_role(files.root, "actor", bundle)  # again, over its own files
    assert stat.S_IMODE(bundle.stat().st_mode) == 0o700
    # `--out .` or `--out /tmp` as root: chmod 700 on the user's folder, or the machine's
    shared = tmp_path / "shared"
    shared.mkdir(mode=0o1777)
    shared.chmod(0o1777)
    (shared / "someone-elses").write_text("x")
    with pytest.raises(SecurityError, match="other files in it: export to a new folder"):
        export_role(files.root, "actor", shared)
    assert stat.S_IMODE(shared.stat().st_mode) == 0o1777 and sorted(p.name for p in shared.iterdir()) == [
        "someone-elses"]


# ---------------------------------------------------------------------------------------------
# An attacker's view: outsiders, insiders stepping outside their part, secrets in messages
# ---------------------------------------------------------------------------------------------

def test_a_damaged_role_config_is_refused_in_one_line_without_its_password(tmp_path: Path, capsys):
    # Zenoh's parser drew the line it stopped at (the password's), serde quoted the value it refused and
    # the validator printed the whole config: a service said the run's password to the terminal and
    # to its log, which other users may read.
    from services.cli import main

    files = init_secure(tmp_path / "secure", RUN)
    password = json.loads(files.credentials.read_text())["users"]["actor"]["password"]
    good = json.loads(files.config("actor").read_text())
    text = files.config("actor").read_text()
    no_user = json.loads(text)
    del no_user["transport"]["auth"]["usrpwd"]["user"]
    queue = json.loads(text)
    queue["transport"]["link"] = {"tx": {"queue": {"size": {"data": 100}}}}
    damaged = {"a stray word": (text.replace(f'"{password}"', f'"{password}" x'), "line 12, column 21: expected"),
               "no quotes": (text.replace(f'"{password}"', password), "line 12, column 21: expected"),
               "cut short": (text[:text.index(password) + 5], "line 12, column 27: expected"),
               "the password as the mode": (json.dumps({**good, "mode": password}),
                                            "unknown variant …, expected one of `router`, `peer`, `client`"),
               "no user": (json.dumps(no_user), "a value Zenoh refuses"),
               "a queue out of range": (json.dumps(queue), "a value Zenoh refuses")}
    # a value that holds serde's own ", expected ", a quote or a backtick: a parse of the message by its quotes
    # let the value's tail through
    variants = {"'expected' in it": f"{password[:6]}, expected {password[6:]}", "a quote in it": f'{password[:6]}"{password[6:]}',
                "a backtick in it": f"{password[:6]}`{password[6:]}"}
    for name, mode in variants.items():
        damaged[f"the password as the mode, {name}"] = (json.dumps({**good, "mode": mode}),
                                                        "unknown variant …, expected one of `router`, `peer`, `client`")
    # Zenoh's own checks quote the value first; a place written in the value came before serde's own
    damaged["an endpoint holding ', expected '"] = (json.dumps({**good, "connect": {"endpoints": [f"x, expected {password}"]}}),
                                                    ": a value Zenoh refuses")
    damaged["a place in the value"] = (json.dumps({**good, "mode": f"--> 77:77 line 77, column 77 {password}"}),
                                       "unknown variant …, expected one of")
    # Zenoh reads a file by its suffix: serde_yaml words its errors otherwise, and TOML's quote the whole file
    damaged["YAML, the password as the mode"] = (f'mode: "{password}"\n', "line 1, column 7: mode: unknown variant …")
    damaged["YAML, the password as a key"] = (f"transport:\n  auth:\n    usrpwd: {{user: u, {password}}}\n",
                                              "transport.auth.usrpwd: unknown field …, expected one of `user`")
    damaged["TOML, the password in a comment"] = (f'mode = "peer"\nzzz = 1\n# , expected {password}\n',
                                                  "unknown field …, expected one of `id`")
    for name, (content, said) in damaged.items():
        bad = tmp_path / ("bad.yaml" if name.startswith("YAML") else "bad.toml" if name.startswith("TOML") else "bad.json5")
        write_secret(bad, {})
        bad.write_text(content)
        with pytest.raises(TransportConfigError) as refused:
            ZenohSettings(config_file=str(bad))
        message = str(refused.value)
        assert password[:5] not in message and password[-5:] not in message, (name, message)
        assert "line 77" not in message and "column 77:" not in message, (name, message)  # the place in the value
        assert "\n" not in message and said in message, (name, message)
        assert message.startswith(f"Zenoh config file {bad} is invalid: ") and ".rs:" not in message, (name, message)
    bad = tmp_path / "bad.json5"
    bad.write_text(damaged["a queue out of range"][0])
    code = main(["evaluator", "--run", RUN, "--runs-dir", str(tmp_path), "--zenoh-config", str(bad)])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and password[:5] not in err and "a value Zenoh refuses" in err, err


def test_an_insider_reaches_nothing_beyond_its_part_with_wildcards_deletes_tokens_or_the_admin_space(tmp_path: Path):
    """Actor, evaluator and viewer credentials against a router with its admin space open (zenohd, the
    compose router, opens it): what passes the router is seen by a subscriber, a queryable and a
    liveliness subscriber of the router itself, which the access control does not filter."""
    import zenoh

    files = init_secure(tmp_path / "secure", RUN)
    config = json.loads(files.router_config.read_text())
    config["adminspace"] = {"enabled": True, "permissions": {"read": True, "write": True}}
    config["transport"]["auth"]["usrpwd"]["dictionary_file"] = str(files.root / "users.txt")
    write_secret(tmp_path / "zenohd.json5", config)
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    p = KEYS.prefix
    keys = [KEYS.transitions("x"), KEYS.weights, KEYS.weights_latest, KEYS.flow, KEYS.config, KEYS.episode_stats("x"),
            KEYS.learner_stats("x"), KEYS.eval_results("x"), f"{p}/other", "cogexplore/other-run/weights", "other/x",
            "cogexplore/@robot/r/reset"]
    wild = ["**", "cogexplore/**", f"{p}/**", f"{p}/*", f"{p}/transitions/*", f"{p}/stats/**", f"{p}/weights/*"]
    own = {"actor": {KEYS.transitions("x"), KEYS.episode_stats("x"), f"{p}/transitions/*"},
           "evaluator": {KEYS.eval_results("x")}, "viewer": set()}
    queries_of = {KEYS.weights_latest, KEYS.config}
    asks = {"actor": queries_of, "evaluator": queries_of, "viewer": set()}
    stats = {KEYS.episode_stats("x"), KEYS.learner_stats("x"), KEYS.eval_results("x")}
    hears = {"actor": {KEYS.weights, KEYS.flow}, "evaluator": {KEYS.weights, KEYS.flow}, "viewer": {KEYS.flow, *stats}}
    alive = {role: KEYS.alive(role, "r") for role in ("learner", "actor", "evaluator")}
    watches = {"actor": {alive["learner"]}, "evaluator": set(), "viewer": set(alive.values())}
    with open_router([endpoint], config_file=str(tmp_path / "zenohd.json5")) as router:
        run_tokens = [router.liveliness().declare_token(key) for key in alive.values()]
        admin = f"@/{router.zid()}"
        assert any(r.ok for r in router.get(f"{admin}/**", timeout=1.0)), "the admin space is open"
        samples: list[tuple[str, str]] = []
        queries: list[str] = []
        tokens: list[tuple[str, str]] = []

        def answer(query) -> None:  # type: ignore[no-untyped-def]
            key = str(query.selector.key_expr)
            queries.append(key)
            if "*" not in key:  # a concrete key is answered as itself (a wildcard query is refused anyway)
                query.reply(key, b"router")

        observers = [router.declare_subscriber("**", lambda s: samples.append((str(s.key_expr), str(s.kind)))),
                     router.declare_queryable("**", answer),
                     router.liveliness().declare_subscriber(
                         "**", lambda s: tokens.append((str(s.key_expr), str(s.kind))))]
        for role in ("actor", "evaluator", "viewer"):
            samples.clear(), queries.clear(), tokens.clear()
            with open_session(ZenohSettings(connect=(endpoint,), config_file=str(files.config(role))),
                              wait_s=2.0) as s:
                for key in keys + wild:
                    s.put(key, b"attack")
                    s.delete(key)
                s.put(f"{admin}/router/config/scouting/delay", b"1")  # the admin space's write access
                held = [s.liveliness().declare_token(k) for k in  # a fake of each role, and wildcards
                        [KEYS.alive(r, role) for r in ("learner", "actor", "evaluator", "router", "trainer")]
                        + [f"{p}/alive/**", f"{p}/alive/learner/*"]]
                replies = {k: [str(r.ok.key_expr) for r in s.get(k, timeout=0.5, target=zenoh.QueryTarget.ALL)
                               if r.ok] for k in keys + wild + [f"{admin}/**", "@/**"]}
                settle(timeout_s=0.5)
                passed = {k for k, kind in samples if "PUT" in kind}, {k for k, kind in samples if "DELETE" in kind}
                heard: set[str] = set()
                watched: set[str] = set()
                subs = [s.declare_subscriber(w, lambda x: heard.add(str(x.key_expr))) for w in wild + keys]
                watch = [s.liveliness().declare_subscriber(w, lambda x: watched.add(str(x.key_expr)), history=True)
                         for w in ("**", f"{p}/alive/**", *(KEYS.all_alive(r) for r in alive))]
                settle(timeout_s=0.5)
                for key in keys:
                    router.put(key, b"the run's data")
                settle(timeout_s=0.5)
                assert heard == hears[role], role
                assert watched - {f"{p}/alive/**", f"{p}/alive/learner/*"} - set(map(lambda r: KEYS.alive(r, role), (
                    "learner", "actor", "evaluator", "router", "trainer"))) == watches[role], role  # less its own
                assert passed == (own[role], set()), role
                assert set(queries) == asks[role], role
                assert {k for k, r in replies.items() if any(not key.startswith("@/") for key in r)} == asks[role], role
                # the session's own admin space answers (its link to the router), the router's does not
                assert {key.split("/")[1] for r in replies.values() for key in r if key.startswith("@/")} <= {
                    str(s.zid())}, role
                declared = {k for k, kind in tokens if "PUT" in kind}  # the last role's going is a DELETE
                assert declared == ({KEYS.alive(role, role)} if role != "viewer" else set()), (role, tokens)
                del held, subs, watch  # kept until here: dropping one undeclares it
        delay = router.get(f"{admin}/router/config/scouting/delay", timeout=1.0)
        assert [r.ok.payload.to_bytes() for r in delay if r.ok] != [b"1"]
        del observers, run_tokens


def test_outsiders_get_no_session_in_any_mode_nor_with_another_runs_credentials_or_certificates(tmp_path: Path):
    bus = Bus(tmp_path / "secure", tls=True)

    def refused(config: Path) -> None:  # no retries: the router is up, a refusal is final
        open_session(ZenohSettings(connect=(bus.endpoint,), config_file=str(config))).close()

    try:
        heard = bus.listen("learner", KEYS.all_transitions)
        for mode in ("peer", "router"):  # these open without a router: they must get none
            config = tmp_path / f"{mode}.json5"
            config.write_text(json.dumps({"mode": mode, "scouting": {"multicast": {"enabled": False}},
                                          "listen": {"endpoints": []}}))
            with open_session(ZenohSettings(connect=(bus.endpoint,), config_file=str(config))) as s:
                settle(lambda: bool(list(s.info.routers_zid())), timeout_s=1.0)
                assert list(s.info.routers_zid()) == [], mode
                s.put(KEYS.transitions("outsider"), b"forged")
        # another run made the same way, and this run's name made again in another folder
        for other in (init_secure(tmp_path / "other", "other", tls=True),
                      init_secure(tmp_path / "again", RUN, tls=True)):
            for role in ROLES:
                # said as a refusal, not as a router that is not there (Zenoh's own words for both)
                with pytest.raises(TransportError, match="takes connections at .* but opened no session: the run's "
                                                         "router refusing"):
                    refused(other.config(role))
            # another run's certificate with this run's CA and password: no TLS link either
            stolen = json.loads(bus.files.config("actor").read_text())
            stolen["transport"]["link"]["tls"].update(
                {"root_ca_certificate": str(bus.files.root / "ca.pem"),
                 "connect_certificate": str(other.root / "actor.pem"),
                 "connect_private_key": str(other.root / "actor.key")})
            write_secret(tmp_path / "stolen.json5", stolen)
            with pytest.raises(TransportError):
                refused(tmp_path / "stolen.json5")
        settle(timeout_s=0.3)
        assert heard == []
    finally:
        bus.close()


def test_idle_connections_do_not_hold_a_tls_router(tmp_path: Path):
    """Anyone may open TCP connections and say nothing. Zenoh admits 100 links at a time into its
    handshake (transport/unicast/accept_pending): on a plain TCP router (`up` on loopback) 100 idle
    connections refuse every new session for as long as they are held. With mutual TLS a link that
    has not shown the run's certificate never reaches those 100: this is why a router that other
    machines reach listens on TLS only."""
    import socket

    bus = Bus(tmp_path / "secure", tls=True)
    idle = []
    try:
        port = int(bus.endpoint.rsplit(":", 1)[1])
        for _ in range(150):
            idle.append(socket.create_connection(("127.0.0.1", port)))
        idle[0].send(bytes.fromhex("160301"))  # and one that starts a TLS record and stops
        settle(timeout_s=0.3)
        session = bus.open("actor")
        session.close()
    finally:
        for sock in idle:
            sock.close()
        bus.close()


def test_secure_init_and_export_say_no_secret(tmp_path: Path, capsys):
    from services.cli import main

    root = tmp_path / "secure"
    assert main(["secure", "init", str(root), "--run", RUN, "--tls"]) == 0
    assert main(["secure", "export", str(root), "--role", "actor", "--out", str(tmp_path / "bundle")]) == 0
    said = "".join(capsys.readouterr())
    secrets = [u["password"] for u in json.loads((root / "credentials.json").read_text())["users"].values()]
    secrets += [line for p in root.glob("*.key") for line in p.read_text().splitlines() if "PRIVATE" not in line]
    assert "actor.json5" in said and not any(secret in said for secret in secrets)
