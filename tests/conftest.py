"""Shared fixtures: small missions and loopback Zenoh sessions (scouting off)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import zenoh

from rover_sim.catalog import load_scene, resolve_scene
from rovergate.config import MissionConfig
from rovergate.session import SessionConfig, free_loopback_port, zenoh_config


@pytest.fixture(scope="session")
def scene():
    return load_scene("arch_field")


def small_config(tmp_path: Path, **overrides) -> MissionConfig:
    cfg = MissionConfig(out=tmp_path / "run", progress=False, **overrides)
    cfg = dataclasses.replace(cfg, ready_timeout_s=90.0, step_timeout_s=90.0)
    resolve_scene(cfg.scene)
    return cfg


@pytest.fixture
def loopback_pair():
    """Two peer sessions linked over an explicit loopback endpoint, scouting off."""
    endpoint = f"tcp/127.0.0.1:{free_loopback_port()}"
    a = zenoh.open(zenoh_config(SessionConfig(listen=(endpoint,))))
    b = zenoh.open(zenoh_config(SessionConfig(connect=(endpoint,))))
    yield endpoint, a, b
    b.close()
    a.close()


def read_metrics(out: Path) -> dict:
    return json.loads((out / "metrics.json").read_text())
