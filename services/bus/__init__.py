"""The Zenoh bus every process of a run meets on: sessions and the router (``session``), the
newest-weights follower of the actors and the evaluator (``follower``). This file holds only where
the bus is by default and how long to wait for it, so that command-line options can name them without
importing Zenoh."""

MODES: tuple[str, ...] = ("peer", "client", "router")
DEFAULT_ROUTER_PORT = 7447
DEFAULT_CONNECT: tuple[str, ...] = (f"tcp/127.0.0.1:{DEFAULT_ROUTER_PORT}",)
"""Where clients look for the router when nothing else is configured."""
DEFAULT_ROUTER_LISTEN: tuple[str, ...] = (f"tcp/0.0.0.0:{DEFAULT_ROUTER_PORT}",)

ENV_CONNECT = "COGEXPLORE_ZENOH_CONNECT"
ENV_LISTEN = "COGEXPLORE_ZENOH_LISTEN"
ENV_CONFIG = "COGEXPLORE_ZENOH_CONFIG"
ENV_MODE = "COGEXPLORE_ZENOH_MODE"
ENV_ROUTER_WAIT = "COGEXPLORE_ZENOH_ROUTER_WAIT_S"
DEFAULT_ROUTER_WAIT_S = 30.0
"""How long a service retries while no router answers: it may start before its router does."""
ZENOHD_DIR = "/secure"
"""Where docker-compose.yml mounts a run's security folder in the router's container."""
ROLES: tuple[str, ...] = ("learner", "actor", "evaluator", "viewer")
"""The roles a run's sessions take, one user each (services.bus.security)."""

