"""A run's bus, closed to everyone but its own services: Zenoh's own authentication and access control.

``cogexplore secure init DIR`` (or ``cogexplore up``, by itself) writes into ``DIR``:

    credentials.json          one user and a random password per role (learner, actor, evaluator, viewer)
    users.txt                 the router's user:password dictionary (``transport/auth/usrpwd``)
    router.json5              the router's config: that dictionary, the access control list (below), and
                              with --tls the TLS listener with client certificates required (mTLS)
    router-zenohd.json5       the same with absolute paths under --zenohd-dir, for the eclipse/zenoh
                              image of docker-compose.yml (zenohd reads paths as they are)
    <role>.json5              each role's client config: its user and password, and with --tls its
                              certificate, key and the run's CA
    ca.pem, ca.key, router.pem, router.key, <role>.pem, <role>.key
                              with --tls: the run's own CA and the certificates it signed (the
                              router's for --host names, each role's with the role as common name)

Every file is readable by its owner only (0600), and a service refuses a secret (every file but the
certificates, ``*.pem``) that group or others may read or write, as ssh refuses such a key: one copied
with a umask of 022 would give the run's passwords to every user of the machine.

The access control list starts from ``default_permission: "deny"`` and allows each role exactly
its part of the run's key space
(``cogexplore/<run>/...``): only the learner puts weights and flow control, answers the weights
and configuration queries and declares the learner's liveliness token; actors only put transitions
and episode stats and declare their own liveliness; the evaluator only reads weights (and flow control, the learner's pulse) and writes
results (both may ask the two queries); a viewer
(the launcher's progress bar, dashboards) only reads statistics and liveliness. Each permission is
given on the flow it travels: ``ingress`` for what a subject sends to the router, ``egress`` for what
the router passes on to it, including the subscriber declarations a publisher must see (a publisher
that is not told of a subscriber sends nothing: a viewer's subscription to ``stats/**`` reaches the
learner only because ``stats/**`` itself is allowed, not merely ``stats/learner/*``).
A session without credentials, with a wrong password, or of a role stepping outside its part gets
nothing through.

Python sessions read a role's config with :class:`services.bus.session.ZenohSettings` (the files it
names are relative to it). ``cogexplore secure export DIR --role actor --out BUNDLE`` copies what
one role needs and nothing else (no other role's password, no CA key) for another machine: put it
in ``runs/<run>/secure/`` there and the actor finds it by itself (``--zenoh-config BUNDLE/actor.json5``
names it anywhere else).

The access rules follow the release: ``secure init DIR --keep`` (what docker-compose.yml runs; ``cogexplore
up`` does the same) rewrites the routers' rules of a folder an older release made, its passwords and
certificates kept; :meth:`SecureFiles.check` refuses such a folder until then.
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
import secrets
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

from services.bus import ROLES, ZENOHD_DIR
from shared.errors import CogexploreError
from shared.files import write_atomically
from shared.wire.keys import ROOT, validate_name

DEFAULT_HOSTS: tuple[str, ...] = ("localhost", "127.0.0.1", "::1")
"""Names the router's TLS certificate is valid for, besides any --host."""
CERT_DAYS = 365
SECRET_PATH_KEYS: tuple[str, ...] = (
    "transport/auth/usrpwd/dictionary_file",
    "transport/link/tls/listen_private_key",
    "transport/link/tls/connect_private_key",
)
"""Config entries that name secret files (the router's passwords, private keys): :func:`check_private`."""
PATH_KEYS: tuple[str, ...] = (
    *SECRET_PATH_KEYS,
    "transport/link/tls/root_ca_certificate",
    "transport/link/tls/listen_certificate",
    "transport/link/tls/connect_certificate",
)
"""Config entries that name files (a relative one is taken relative to its config file)."""
PASSWORD_KEY = "transport/auth/usrpwd/password"
"""The config entry that makes a config file a secret itself."""


class SecurityError(CogexploreError):
    """Security files that are missing, incomplete, of another run or open to other users."""


def check_private(path: str | Path) -> None:
    """Raise SecurityError when group or others may read or write the secret file ``path`` (a
    password, a private key): what init and export write is 0600."""
    mode = stat.S_IMODE(os.stat(path).st_mode)
    if mode & 0o077:
        raise SecurityError(f"{path} holds secrets but other users may read or write it (mode {mode:04o}): "
                            f"run `chmod 600 {path}`")


# ---------------------------------------------------------------------------------------------
# The access control list
# ---------------------------------------------------------------------------------------------

def _grants(run: str) -> dict[str, list[tuple[str, list[str], list[str]]]]:
    """role -> [(flow, messages, key expressions)]: everything a role may do on run ``run``."""
    p = f"{ROOT}/{validate_name(run, 'run name')}"
    transitions, weights, latest, flow = f"{p}/transitions/*", f"{p}/weights", f"{p}/weights/latest", f"{p}/flow"
    config = f"{p}/config"
    stats = f"{p}/stats/**"
    alive = {role: f"{p}/alive/{role}/*" for role in ("learner", "actor", "evaluator")}
    sub, pub, token = "declare_subscriber", "put", "liveliness_token"
    watch = ["declare_liveliness_subscriber", "liveliness_query"]
    return {
        "learner": [
            ("ingress", [pub], [weights, flow, f"{p}/stats/learner/*"]),
            ("ingress", [sub], [transitions]),
            ("egress", [pub], [transitions]),
            ("egress", [sub], [weights, flow, f"{p}/stats/learner/*", stats]),  # who listens to what it puts
            ("ingress", ["declare_queryable", "reply"], [latest, config]),
            ("egress", ["query"], [latest, config]),
            ("ingress", [token], [alive["learner"]]),
            ("ingress", watch, [alive["actor"]]),
            ("egress", [token], [alive["actor"]]),
        ],
        "actor": [
            ("ingress", [pub], [transitions, f"{p}/stats/episode/*"]),
            ("egress", [sub], [transitions, f"{p}/stats/episode/*", stats]),
            ("ingress", [sub], [weights, flow]),
            ("egress", [pub], [weights, flow]),
            ("ingress", ["query"], [latest, config]),
            ("egress", ["declare_queryable", "reply"], [latest, config]),
            ("ingress", [token], [alive["actor"]]),
            ("ingress", watch, [alive["learner"]]),
            ("egress", [token], [alive["learner"]]),
        ],
        "evaluator": [
            ("ingress", [sub], [weights, flow]),  # flow control: the learner's pulse
            ("egress", [pub], [weights, flow]),
            ("ingress", ["query"], [latest, config]),
            ("egress", ["declare_queryable", "reply"], [latest, config]),
            ("ingress", [pub], [f"{p}/stats/eval/*"]),
            ("egress", [sub], [f"{p}/stats/eval/*", stats]),
            ("ingress", [token], [alive["evaluator"]]),
        ],
        "viewer": [
            ("ingress", [sub], [stats, flow]),
            ("egress", [pub], [stats, flow]),
            ("ingress", watch, [f"{p}/alive/**"]),
            ("egress", [token], [f"{p}/alive/**"]),
        ],
    }


def access_control(run: str, users: dict[str, str], tls: bool = False) -> dict[str, Any]:
    """The ``access_control`` section for ``run``: deny by default, each role's grants for its user
    (and, with ``tls``, only over a link whose client certificate names the role)."""
    rules, policies, subjects = [], [], []
    for role, grants in _grants(run).items():
        subject = {"id": role, "usernames": [users[role]]}
        if tls:
            subject["cert_common_names"] = [role]
        subjects.append(subject)
        ids = []
        for k, (flow, messages, key_exprs) in enumerate(grants):
            ids.append(f"{role}-{k}")
            rules.append({"id": ids[-1], "permission": "allow", "flows": [flow], "messages": messages,
                          "key_exprs": key_exprs})
        policies.append({"id": role, "rules": ids, "subjects": [role]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


# ---------------------------------------------------------------------------------------------
# The files
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class SecureFiles:
    """The security folder of a run (see the module docstring)."""

    root: Path

    @property
    def credentials(self) -> Path:
        return self.root / "credentials.json"

    @property
    def router_config(self) -> Path:
        return self.root / "router.json5"

    def config(self, role: str) -> Path:
        """The client config of ``role``."""
        if role not in ROLES:
            raise SecurityError(f"role {role!r} is unknown; roles: {list(ROLES)}")
        return self.root / f"{role}.json5"

    @property
    def tls(self) -> bool:
        """The folder holds a CA and certificates (links are TLS with client certificates)."""
        return (self.root / "ca.pem").is_file()

    def _credentials(self, fix: str = "") -> dict[str, Any]:
        """The credentials file's content; SecurityError naming ``secure init`` (with ``fix``) when
        it is missing or unreadable."""
        if self.credentials.is_file():
            check_private(self.credentials)  # not in the try below: a SecurityError is a ValueError
        try:
            content = json.loads(self.credentials.read_text())
            if not isinstance(content, dict):
                raise TypeError("not a JSON object")
            return content
        except (OSError, ValueError, TypeError, RecursionError) as exc:
            raise SecurityError(f"{self.credentials} is missing or unreadable ({exc}): run "
                                f"`cogexplore secure init {self.root}{fix}`") from None

    def meta(self) -> dict[str, Any]:
        """What ``init`` recorded: the run, whether TLS, the router's names."""
        meta = self._credentials().get("meta")
        if not isinstance(meta, dict):
            raise SecurityError(f"{self.credentials} is missing or unreadable (no meta): run "
                                f"`cogexplore secure init {self.root}`")
        return meta

    def check(self, run: str, tls: bool = False) -> "SecureFiles":
        """Raise SecurityError unless the folder is complete, made for ``run``, and has TLS when asked."""
        meta = self.meta()
        if meta.get("run") != run:
            raise SecurityError(f"{self.root} was made for run {meta.get('run')!r}, not {run!r}")
        missing = [p.name for p in (self.router_config, *map(self.config, ROLES)) if not p.is_file()]
        if missing:
            raise SecurityError(f"{self.root} lacks {', '.join(missing)}: run `cogexplore secure init {self.root}`")
        if tls and not self.tls:  # init refuses a folder with credentials unless forced
            raise SecurityError(f"{self.root} has no TLS certificates: run `cogexplore secure init {self.root} "
                                "--tls --host <this machine's name> --force` (links that leave the machine need TLS; "
                                "the passwords are made anew too: export the bundles of actors elsewhere again)")
        if self.tls and (expired := self.expired_certificate()) is not None:
            name, when = expired
            raise SecurityError(f"{self.root / name} expired on {when:%Y-%m-%d %H:%M} UTC (certificates last "
                                f"{CERT_DAYS} days): run `cogexplore secure init {self.root} --tls --host <this "
                                "machine's name> --force` for new ones (and new passwords: export the bundles again)")
        if self.outdated_rules(run):
            raise SecurityError(f"{self.router_config}'s access rules are not this release's (a folder made by an "
                                f"older one: some service would be refused its part): run `cogexplore secure init "
                                f"{self.root} --keep`, which rewrites them and keeps the passwords and certificates")
        return self

    def expired_certificate(self, now: datetime.datetime | None = None) -> tuple[str, datetime.datetime] | None:
        """(file name, end of validity) of the first certificate here past its end, or None. The router
        refuses every link it signs, a service's or its own clients', with the same silence as a router
        that is not there: said here instead, where the run starts."""
        from cryptography import x509

        now = now or datetime.datetime.now(datetime.UTC)
        for name in ("ca.pem", "router.pem", *(f"{role}.pem" for role in ROLES)):
            try:
                cert = x509.load_pem_x509_certificate((self.root / name).read_bytes())
            except (OSError, ValueError):  # absent (an exported bundle holds its role's alone) or unreadable:
                continue                   # the TLS handshake says so
            if cert.not_valid_after_utc <= now:
                return name, cert.not_valid_after_utc
        return None

    def current_rules(self, run: str) -> dict[str, Any]:
        """The access control this release gives ``run``'s users (those of the credentials file)."""
        users = self._credentials(" --force").get("users")
        try:
            names = {role: users[role]["user"] for role in ROLES}
        except (KeyError, TypeError) as exc:
            raise SecurityError(f"{self.credentials} is missing or unreadable (users: {exc}): run "
                                f"`cogexplore secure init {self.root} --force`") from None
        return access_control(run, names, self.tls)

    def _router_configs(self) -> list[tuple[Path, Any]]:
        """Each router config there is and its content (None where it does not read as JSON)."""
        out = []
        for path in (self.router_config, self.root / "router-zenohd.json5"):
            if path.is_file():
                try:
                    out.append((path, json.loads(path.read_text())))
                except (OSError, ValueError, RecursionError):
                    out.append((path, None))
        return out

    def outdated_rules(self, run: str) -> list[Path]:
        """The router configs whose access control differs from :meth:`current_rules` (files written
        by an older release, whose rules lack what a service now needs)."""
        rules = self.current_rules(run)
        return [path for path, config in self._router_configs()
                if not isinstance(config, dict) or config.get("access_control") != rules]

    def refresh_rules(self, run: str) -> list[Path]:
        """Rewrite the access control of the router configs that are :meth:`outdated_rules`, the rest of
        each file (passwords, certificates, paths) as it is; returns the files rewritten."""
        rules, rewritten = self.current_rules(run), []
        for path, config in self._router_configs():
            if not isinstance(config, dict):
                raise SecurityError(f"{path} is not a readable router config: run `cogexplore secure init "
                                    f"{self.root} --force`")
            if config.get("access_control") != rules:
                _write_private(path, _json5({**config, "access_control": rules}))
                rewritten.append(path)
        return rewritten


def _write_private(path: Path, text: str | bytes) -> None:
    def write(tmp: Path) -> None:  # created 0600: never readable by others, not even for a moment
        # created anew: a file or link left at that name (a killed writer, a planted link) would keep its
        # own mode, or take the secret where it points
        tmp.unlink(missing_ok=True)
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
        with os.fdopen(fd, "wb") as fh:
            fh.write(text.encode() if isinstance(text, str) else text)

    write_atomically(path, write)


def _json5(obj: Any) -> str:
    return json.dumps(obj, indent=2) + "\n"  # JSON is JSON5


def init_secure(root: str | Path, run: str, *, tls: bool = False, hosts: Sequence[str] = (),
                zenohd_dir: str = ZENOHD_DIR, force: bool = False) -> SecureFiles:
    """Write the security folder of ``run`` (see the module docstring). An existing complete folder
    is kept unless ``force`` (new passwords and certificates: every service must restart with them)."""
    files = SecureFiles(Path(root))
    validate_name(run, "run name")
    if files.credentials.exists() and not force:
        raise SecurityError(f"{files.root} already holds credentials: pass --force to replace them (every "
                            "service of the run then needs the new files)")
    files.root.mkdir(parents=True, exist_ok=True)
    os.chmod(files.root, 0o700)
    # The credentials file says the folder is complete (--keep keeps it, init refuses it without --force):
    # written last, and an old one removed first, so that a folder cut short (a full disk, a kill) is
    # made anew by the next init rather than kept with half its files or mixing two sets of passwords.
    files.credentials.unlink(missing_ok=True)
    users = {role: f"{run}-{role}" for role in ROLES}
    passwords = {role: secrets.token_urlsafe(24) for role in ROLES}
    names = list(dict.fromkeys([*DEFAULT_HOSTS, *hosts]))
    _write_private(files.root / "users.txt", "".join(f"{users[r]}:{passwords[r]}\n" for r in ROLES))
    if tls:
        _write_certificates(files.root, names)
    else:
        for name in ("ca", "router", *ROLES):
            for ext in ("pem", "key"):
                (files.root / f"{name}.{ext}").unlink(missing_ok=True)

    def router(prefix: str) -> dict[str, Any]:
        link = {"tls": {"root_ca_certificate": f"{prefix}ca.pem", "listen_certificate": f"{prefix}router.pem",
                        "listen_private_key": f"{prefix}router.key", "enable_mtls": True}} if tls else {}
        return {"mode": "router", "scouting": {"multicast": {"enabled": False}},
                "transport": {"auth": {"usrpwd": {"dictionary_file": f"{prefix}users.txt"}}, "link": link},
                "access_control": access_control(run, users, tls)}

    _write_private(files.router_config, _json5(router("")))
    _write_private(files.root / "router-zenohd.json5", _json5(router(zenohd_dir.rstrip("/") + "/")))
    for role in ROLES:
        transport: dict[str, Any] = {"auth": {"usrpwd": {"user": users[role], "password": passwords[role]}}}
        if tls:
            transport["link"] = {"tls": {"root_ca_certificate": "ca.pem", "connect_certificate": f"{role}.pem",
                                         "connect_private_key": f"{role}.key", "enable_mtls": True}}
        _write_private(files.config(role), _json5({"mode": "client", "scouting": {"multicast": {"enabled": False}},
                                                   "transport": transport}))
    _write_private(files.credentials, _json5({
        "meta": {"run": run, "tls": tls, "hosts": names, "created": datetime.datetime.now(datetime.UTC).isoformat()},
        "users": {role: {"user": users[role], "password": passwords[role]} for role in ROLES}}))
    return files


def _write_certificates(root: Path, hosts: Sequence[str]) -> None:
    """The run's CA, the router's certificate for ``hosts`` and one client certificate per role."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    now = datetime.datetime.now(datetime.UTC)

    def key_pem(key: Any) -> bytes:
        return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                 serialization.NoEncryption())

    def name(cn: str) -> x509.Name:
        return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "cogexplore"),
                          x509.NameAttribute(NameOID.COMMON_NAME, cn)])

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca = (x509.CertificateBuilder().subject_name(name("cogexplore run CA")).issuer_name(name("cogexplore run CA"))
          .public_key(ca_key.public_key()).serial_number(x509.random_serial_number())
          .not_valid_before(now - datetime.timedelta(minutes=5)).not_valid_after(now + datetime.timedelta(days=CERT_DAYS))
          .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
          .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True, content_commitment=False,
                                       key_encipherment=False, data_encipherment=False, key_agreement=False,
                                       encipher_only=False, decipher_only=False), critical=True)
          .sign(ca_key, hashes.SHA256()))
    _write_private(root / "ca.key", key_pem(ca_key))
    _write_private(root / "ca.pem", ca.public_bytes(serialization.Encoding.PEM))

    def issue(cn: str, usage: Any, alt_names: Sequence[str]) -> None:
        key = ec.generate_private_key(ec.SECP256R1())
        sans = []
        for h in alt_names:
            try:
                sans.append(x509.IPAddress(ipaddress.ip_address(h)))
            except ValueError:
                sans.append(x509.DNSName(h))
        builder = (x509.CertificateBuilder().subject_name(name(cn)).issuer_name(ca.subject)
                   .public_key(key.public_key()).serial_number(x509.random_serial_number())
                   .not_valid_before(now - datetime.timedelta(minutes=5))
                   .not_valid_after(now + datetime.timedelta(days=CERT_DAYS))
                   .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                   .add_extension(x509.ExtendedKeyUsage([usage]), critical=False))
        if sans:
            builder = builder.add_extension(x509.SubjectAlternativeName(sans), critical=False)
        _write_private(root / f"{cn}.key", key_pem(key))
        _write_private(root / f"{cn}.pem", builder.sign(ca_key, hashes.SHA256()).public_bytes(serialization.Encoding.PEM))

    issue("router", ExtendedKeyUsageOID.SERVER_AUTH, hosts)
    for role in ROLES:
        issue(role, ExtendedKeyUsageOID.CLIENT_AUTH, [role])


def export_role(root: str | Path, role: str, out: str | Path) -> list[Path]:
    """Copy what one role needs to join from another machine into ``out`` (its config and, with TLS,
    the CA certificate and its own certificate and key); nothing of the other roles, nor the CA's
    key. Returns the files written."""
    files = SecureFiles(Path(root))
    names = [files.config(role).name] + (["ca.pem", f"{role}.pem", f"{role}.key"] if files.tls else [])
    missing = [n for n in names if not (files.root / n).is_file()]
    if missing:
        raise SecurityError(f"{files.root} lacks {', '.join(missing)}: run `cogexplore secure init {files.root}`")
    for n in names:
        if not n.endswith(".pem"):  # a certificate is public, the rest secret
            check_private(files.root / n)
    target = Path(out)
    target.mkdir(parents=True, exist_ok=True)
    if stat.S_IMODE(target.stat().st_mode) & 0o077:
        # a folder of its own is closed to others; one that holds more (`--out .`, `--out /tmp` as root)
        # is not the export's to chmod
        if any(p.name not in names for p in target.iterdir()):
            raise SecurityError(f"{target} is a folder other users may open, with other files in it: export to "
                                "a new folder (it is made readable by its owner only)")
        os.chmod(target, 0o700)
    written = []
    for n in names:
        _write_private(target / n, (files.root / n).read_bytes())
        written.append(target / n)
    return written


def run_secure_init(args: Any) -> int:
    """``cogexplore secure init``."""
    run = args.run or Path(args.dir).resolve().parent.name
    files = SecureFiles(Path(args.dir))
    if args.keep and files.credentials.exists():
        # A complete folder of this run keeps its passwords and certificates (compose restarts); only
        # access rules an older release wrote are brought up to this one's.
        if files.meta().get("run") == run:
            files.refresh_rules(run)
        files.check(run, tls=args.tls)
    else:
        files = init_secure(args.dir, run, tls=args.tls, hosts=args.host, zenohd_dir=args.zenohd_dir,
                            force=args.force)
    print(json.dumps({"dir": str(files.root), "run": run, "tls": files.tls, "roles": list(ROLES),
                      "router_config": str(files.router_config)}, indent=2))
    return 0


def run_secure_export(args: Any) -> int:
    """``cogexplore secure export``."""
    written = export_role(args.dir, args.role, args.out)
    print(json.dumps({"role": args.role, "files": [str(p) for p in written],
                      "join": f"--zenoh-config {written[0]}"}, indent=2))
    return 0
