"""compose.yaml as a plant's IT department reads it: nobody is root, the router has a
healthcheck the services wait for, the bus is on 127.0.0.1 unless told, ./runs is the
invoking user's, and every container runs with the configs `autotune up --secure` writes
(the spec itself is checked by tests/integration/test_main_job.py)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from services.up import ROLES, SecureDeployment

ROOT = Path(__file__).resolve().parents[1]
yaml = pytest.importorskip("ruamel.yaml", reason="ruamel.yaml comes with check-jsonschema")


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.YAML(typ="safe").load((ROOT / "compose.yaml").read_text())


def test_no_container_runs_as_root_and_none_can_gain_privileges(compose) -> None:
    for name, service in compose["services"].items():
        assert service["user"] == "${UID:-1000}:${GID:-1000}", name
        assert service["cap_drop"] == ["ALL"] and service["read_only"] is True, name
        assert "no-new-privileges:true" in service["security_opt"], name
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert re.search(r"^USER 1000:1000$", dockerfile, re.M)  # the image alone is not root


def test_the_router_is_healthchecked_and_the_services_wait_for_it(compose) -> None:
    services = compose["services"]
    assert "1D17" in " ".join(services["router"]["healthcheck"]["test"])  # 7447 in hex
    assert f"{7447:04X}" == "1D17"
    for name in ("plant_sim", "autotuner", "logger"):
        assert services[name]["depends_on"]["router"]["condition"] == "service_healthy"


def test_the_bus_is_on_loopback_unless_told_and_runs_are_never_created_as_root(compose) -> None:
    (port,) = compose["services"]["router"]["ports"]
    assert port == "${AUTOTUNE_BUS_BIND:-127.0.0.1}:7447:7447"
    (runs,) = [v for v in compose["services"]["logger"]["volumes"] if isinstance(v, dict)]
    assert (runs["source"], runs["target"], runs["bind"]["create_host_path"]) == (
        "./runs",
        "/runs",
        False,
    )


def test_every_container_uses_the_secure_configs_autotune_up_writes(compose, tmp_path) -> None:
    deployment = SecureDeployment(tmp_path, "tcp/router:7447")
    router = compose["services"]["router"]
    assert router["command"][:2] == ["-c", f"/secure/{deployment.router.name}"]
    roles = {"plant_sim": "plant", "autotuner": "tuner", "logger": "logger"}
    for name, role in roles.items():
        command = compose["services"][name]["command"]
        assert f"/secure/{deployment.config(role).name}" in command, name
        check = compose["services"][name]["healthcheck"]["test"]
        assert f"/secure/{deployment.config('viewer').name}" in check, name
    assert set(roles.values()) | {"viewer"} <= set(ROLES)


def test_each_container_mounts_only_its_own_secrets(compose, tmp_path) -> None:
    """A service's container holds its own role's config and the viewer's (its
    healthcheck's), never another role's password: with the whole secure directory in every
    container a compromised plant could log in as the tuner, the only role allowed to
    command loops (helper review)."""
    deployment = SecureDeployment(tmp_path, "tcp/router:7447")
    own = {
        "router": {deployment.router.name, "users.txt"},
        "plant_sim": {deployment.config("plant").name, deployment.config("viewer").name},
        "autotuner": {deployment.config("tuner").name, deployment.config("viewer").name},
        "logger": {deployment.config("logger").name, deployment.config("viewer").name},
    }
    for name, files in own.items():
        mounted = [v for v in compose["services"][name]["volumes"] if isinstance(v, str)]
        assert all(v.endswith(":ro") for v in mounted), (name, mounted)
        targets = {v.split(":")[1] for v in mounted}
        assert targets == {f"/secure/{f}" for f in files}, (name, targets)
        for v in mounted:  # each from its file in .autotune/secure, not the directory
            source, target, _ = v.split(":")
            assert source == f"./.autotune/secure/{Path(target).name}", v
