"""deploy/ checked by the tools that run here: the Dockerfile parsed by BuildKit's parser (the
`dockerfile` wheel: pinned base image, CPU torch pinned before the package, a non-root user, exec-form
CMD; every image of compose and Kubernetes pinned, none `latest`; the API probed), every YAML file parses (and the Kubernetes objects
have their kind, name and the fixes the issue asked for), the SLURM script is valid bash with the
batch-shell signal, its worker command runs locally against a real store, script arguments reach
every worker and a failing worker fails the script (tests/service/test_slurm.py runs it on SLURM)."""

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
    # Arguments after the script go to every worker, and a failing worker fails the array task
    # (its status is the script's): an invalid lease is refused by both workers with status 2.
    out = subprocess.run(["bash", str(script), "--lease-seconds", "0"], env=env, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 2, (out.returncode, out.stderr[-2000:])
    assert out.stderr.count("--lease-seconds must be > 0") == 2, out.stderr[-2000:]


# --- the Dockerfile, parsed by BuildKit's own parser (the `dockerfile` wheel) ---

def _dockerfile():
    import dockerfile

    return dockerfile.parse_file(str(DEPLOY / "Dockerfile"))


def _image_refs() -> list[tuple[str, str]]:
    """(where, image) of every image the deploy files name: FROM lines, compose, Kubernetes."""
    refs = [("Dockerfile", c.value[0]) for c in _dockerfile() if c.cmd == "FROM"]
    for path in sorted(DEPLOY.rglob("*.yaml")):
        for doc in yaml.safe_load_all(path.read_text()):
            stack = [doc]
            while stack:
                node = stack.pop()
                if isinstance(node, dict):
                    refs += [(path.name, v) for k, v in node.items() if k == "image" and isinstance(v, str)]
                    stack += list(node.values())
                elif isinstance(node, list):
                    stack += node
    return refs


def test_every_image_is_pinned_to_a_version_never_latest():
    import re

    refs = _image_refs()
    assert len(refs) >= 5, refs
    for where, ref in refs:
        last = ref.split("@")[0].split("/")[-1]
        tag = last.partition(":")[2]
        assert tag and tag != "latest", f"{where}: image {ref!r} has no pinned tag"
        # A release, not a moving line: python:3.11.7-slim-bookworm (not 3.11-slim), postgres:16.6-bookworm
        # (not 16), bssrdf-db:0.1.0.
        patch = ref.startswith("python:")
        assert re.match(r"\d+\.\d+\.\d+" if patch else r"\d+\.\d+", tag), f"{where}: {ref!r} is a moving tag"


def test_dockerfile_installs_pinned_cpu_torch_before_the_package_and_runs_as_a_user():
    cmds = _dockerfile()
    runs = [(i, c.value[0]) for i, c in enumerate(cmds) if c.cmd == "RUN"]
    torch = [(i, r) for i, r in runs if "torch" in r]
    package = [i for i, r in runs if r.startswith("pip install") and r.endswith(" .")]
    assert len(torch) == 1 and len(package) == 1, runs
    i_torch, torch_run = torch[0]
    assert "torch==" in torch_run and "--index-url https://download.pytorch.org/whl/cpu" in torch_run, torch_run
    assert i_torch < package[0], "torch must come from the CPU index before the package pulls a default build"
    assert "-c constraints.txt" in dict(runs)[package[0]], \
        "the package's dependencies come from the lock"
    # The same torch as the package pins, so `pip install .` finds it installed and pulls no other build.
    import tomllib

    deps = tomllib.loads((DEPLOY.parent / "pyproject.toml").read_text())["project"]["dependencies"]
    (pin,) = [d.replace(" ", "") for d in deps if d.replace(" ", "").startswith("torch")]
    assert pin.startswith("torch==") and pin in torch_run.split(), (pin, torch_run)
    users = [c.value[0] for c in cmds if c.cmd == "USER"]
    assert users and users[-1] not in ("root", "0"), users
    assert not any(c.cmd == "ADD" for c in cmds), "COPY, not ADD"
    for c in cmds:
        if c.cmd in ("CMD", "ENTRYPOINT"):
            assert c.json, f"{c.cmd} in exec (JSON) form, so SIGTERM reaches the worker: {c.original}"
        if c.cmd == "WORKDIR":
            assert c.value[0].startswith("/"), c.original
        if c.cmd == "RUN" and "|" in c.value[0]:
            assert "pipefail" in c.value[0], f"a pipe without pipefail hides a failed step: {c.original}"
        if c.cmd == "RUN" and "apt-get install" in c.value[0]:
            assert "--no-install-recommends" in c.value[0] and "rm -rf /var/lib/apt/lists" in c.value[0], c.original


def test_the_api_has_a_health_probe_everywhere_it_runs():
    has_healthcheck = any(c.cmd == "HEALTHCHECK" for c in _dockerfile())
    compose = yaml.safe_load((DEPLOY / "compose.yaml").read_text())
    assert has_healthcheck or "/healthz" in str(compose["services"]["api"]["healthcheck"]["test"])
    api = next(d for d in yaml.safe_load_all((DEPLOY / "k8s" / "api.yaml").read_text()) if d["kind"] == "Deployment")
    (container,) = api["spec"]["template"]["spec"]["containers"]
    assert container["readinessProbe"]["httpGet"]["path"] == "/readyz"
    assert container["livenessProbe"]["httpGet"]["path"] == "/healthz"
