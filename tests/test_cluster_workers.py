"""Workers on a cluster are the cluster's (issue 71): `dlo online --executor ray --ray-address
HEAD --workers 8` runs against a Ray instance of 8 logical CPUs on a machine with fewer; more
workers than the cluster's CPUs is one line, exit 2, nothing written; without an address the
cap stays this machine's CPUs."""

from __future__ import annotations

import json

import pytest
from typer.testing import CliRunner

from dlocli.cli import app
from dlocli.limits import MAX_PROCESSES

ray = pytest.importorskip("ray")
runner = CliRunner()
TINY = ["--iters", "1", "--trials", "2", "--steps", "5", "--epochs", "1",
        "--initial-episodes", "2", "--hidden", "8", "--seed", "3"]  # fmt: skip
CLUSTER_CPUS = 8


@pytest.fixture(scope="module")
def cluster8():
    """A Ray instance claiming 8 CPUs, whatever this machine has; runs join its address."""
    ray.init(num_cpus=CLUSTER_CPUS, include_dashboard=False, log_to_driver=False)
    try:
        yield ray.get_runtime_context().gcs_address
    finally:
        ray.shutdown()


def online(*args: str) -> tuple[int, str]:
    res = runner.invoke(app, ["online", *TINY, "--executor", "ray", *args, "--json"])
    return res.exit_code, res.output


def test_workers_up_to_the_clusters_cpus_run(cluster8, tmp_path):
    out = tmp_path / "run"
    code, output = online("--ray-address", cluster8, "--workers", str(CLUSTER_CPUS),
                          "--out", str(out))  # fmt: skip
    assert code == 0, output
    assert json.loads((out / "spec.json").read_text())["workers"] == CLUSTER_CPUS
    assert json.loads(output.strip().splitlines()[-1])["iterations_done"] == 1


def test_more_workers_than_the_clusters_cpus_is_one_line(cluster8, tmp_path):
    out = tmp_path / "run"
    code, output = online("--ray-address", cluster8, "--workers", str(CLUSTER_CPUS + 1),
                          "--out", str(out))  # fmt: skip
    assert code == 2, output
    line = output.strip()
    assert line.count("\n") == 0 and f"has {CLUSTER_CPUS} CPUs" in line, line
    assert f"--workers {CLUSTER_CPUS} or fewer" in line
    assert not out.exists()


@pytest.mark.skipif(MAX_PROCESSES >= CLUSTER_CPUS, reason="this machine has the CPUs")
@pytest.mark.parametrize("executor", [[], ["--executor", "ray"]], ids=["local", "ray-local"])
def test_without_an_address_workers_are_this_machines(executor, tmp_path):
    out = tmp_path / "run"
    res = runner.invoke(app, ["online", *TINY, *executor, "--workers", str(CLUSTER_CPUS),
                              "--out", str(out)])  # fmt: skip
    assert res.exit_code == 2, res.output
    line = res.output.strip()
    assert line.count("\n") == 0 and f"at most {MAX_PROCESSES} on this machine" in line, line
    assert "--ray-address" in line and not out.exists()
