"""deploy/ checked by the tools that run here: every YAML file parses (and the Kubernetes objects
have their kind, name and the fixes the issue asked for), the SLURM script is valid bash with the
batch-shell signal, and its worker command runs locally against a real store."""

from __future__ import annotations

import configparser
import os
import subprocess
import sys
from pathlib import Path

import yaml

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"


def test_every_yaml_file_parses_and_names_its_objects():
    files = sorted(DEPLOY.rglob("*.yaml"))
    assert len(files) >= 5
    for path in files:
        docs = [d for d in yaml.safe_load_all(path.read_text()) if d is not None]
        assert docs, path
        if path.parent.name == "k8s":
            for d in docs:
                assert d["apiVersion"] and d["kind"] and d["metadata"]["name"], path


def test_k8s_workers_share_a_kernel_cache_and_have_room_for_a_merge():
    docs = list(yaml.safe_load_all((DEPLOY / "k8s" / "worker.yaml").read_text()))
    deployment = next(d for d in docs if d["kind"] == "Deployment")
    pvc = next(d for d in docs if d["kind"] == "PersistentVolumeClaim")
    pod = deployment["spec"]["template"]["spec"]
    (container,) = pod["containers"]
    env = {e["name"]: e["value"] for e in container["env"]}
    mount = {m["name"]: m["mountPath"] for m in container["volumeMounts"]}
    assert env["BSSRDF_KERNEL_CACHE"] == mount["kernels"]
    assert pod["volumes"][0]["persistentVolumeClaim"]["claimName"] == pvc["metadata"]["name"]
    assert "ReadWriteMany" in pvc["spec"]["accessModes"]
    assert container["resources"]["limits"]["memory"] == "4Gi"


def test_pgbouncer_config_is_transaction_pooling():
    ini = configparser.ConfigParser()
    ini.read(DEPLOY / "pgbouncer" / "pgbouncer.ini")
    assert ini["pgbouncer"]["pool_mode"] == "transaction" and int(ini["pgbouncer"]["max_client_conn"]) >= 2000


def test_slurm_script_is_valid_bash_signals_the_batch_shell_and_its_workers_run(tmp_path):
    script = DEPLOY / "slurm" / "worker-array.sh"
    subprocess.run(["bash", "-n", str(script)], check=True)
    assert "#SBATCH --signal=B:TERM@" in script.read_text()
    # The script's own worker command, locally: an empty SQLite store, two "CPUs": both --once
    # workers find no work that could appear and exit 0, and so does the script.
    env = {**os.environ, "BSSRDF_DATABASE_URL": f"sqlite:///{tmp_path / 'jobs.sqlite'}",
           "BSSRDF_STORAGE_URI": str(tmp_path / "data"), "SLURM_CPUS_PER_TASK": "2",
           "BSSRDF_COMMAND": f"{sys.executable} -m service.cli", "PYTHONPATH": str(DEPLOY.parent)}
    out = subprocess.run(["bash", str(script)], env=env, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stderr.count('"worker stopped"') == 2, out.stderr[-2000:]
