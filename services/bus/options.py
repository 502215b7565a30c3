"""The options of ``cogexplore secure init`` (light: no Zenoh, no cryptography)."""

from __future__ import annotations

import argparse

from services.bus import ROLES, ZENOHD_DIR


def add_secure_init_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", metavar="DIR", help="the folder to write, e.g. runs/<run>/secure (what `cogexplore up` uses)")
    p.add_argument("--run", default=None, help="the run the access control is for (default: the name of DIR's parent)")
    p.add_argument("--tls", action="store_true",
                   help="also a CA, the router's certificate and one per role: TLS with client certificates, needed "
                        "wherever the router listens beyond this machine")
    p.add_argument("--host", action="append", default=[], metavar="NAME",
                   help="a name or address the router's certificate is valid for, besides localhost and 127.0.0.1 "
                        "(repeatable): the one remote actors connect to")
    p.add_argument("--zenohd-dir", default=ZENOHD_DIR, metavar="PATH",
                   help=f"where router-zenohd.json5 expects the folder in the router's container (default {ZENOHD_DIR})")
    keep = p.add_mutually_exclusive_group()
    keep.add_argument("--force", action="store_true",
                      help="replace existing credentials (every service then needs the new files)")
    keep.add_argument("--keep", action="store_true",
                      help="keep a complete folder of this run as it is, writing one only where there is none "
                           "(what docker-compose.yml runs at every start)")


def add_secure_export_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", metavar="DIR", help="the run's security folder (from `cogexplore secure init`)")
    p.add_argument("--role", default="actor", choices=ROLES, help="the role to export (default actor)")
    p.add_argument("--out", required=True, metavar="DIR", help="the folder to write (copy it to the other machine)")
