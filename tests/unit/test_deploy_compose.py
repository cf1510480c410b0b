"""The compose file publishes the API alone beyond this host: Redis (no password), MinIO and Flower (no
authentication; it can revoke and terminate tasks) listen on 127.0.0.1 unless an operator names another address."""

from __future__ import annotations

import re
from pathlib import Path

COMPOSE = Path(__file__).resolve().parents[2] / "docker-compose.yml"
_SERVICE = re.compile(r"^  ([a-z][\w-]*):\n((?:(?:    .*)?\n)*)", re.M)
_PORT = re.compile(r'^      - "([^"]+)"$', re.M)
LOCAL = re.compile(r"^\$\{SYMGS_[A-Z0-9_]+_BIND:-127\.0\.0\.1\}:")


def published_ports() -> dict[str, list[str]]:
    services = COMPOSE.read_text().split("\nservices:\n", 1)[1].split("\nvolumes:\n", 1)[0] + "\n"
    ports = {}
    for name, body in _SERVICE.findall(services):
        section = body.split("    ports:\n", 1)
        if len(section) == 2:
            ports[name] = _PORT.findall(re.split(r"^    \S", section[1], maxsplit=1, flags=re.M)[0])
    return ports


def test_only_the_api_is_published_beyond_this_host() -> None:
    ports = published_ports()
    assert {"api", "redis", "minio", "flower"} <= set(ports), ports
    for name, mappings in ports.items():
        assert mappings, name
        if name != "api":
            assert all(LOCAL.match(mapping) for mapping in mappings), (name, mappings)
