"""A one-node SLURM cluster of the test's own: ``munged`` with its own key and socket, ``slurmctld``
and ``slurmd`` on this machine, every file (config, state, spool, logs, pid files) in one temporary
directory, on free ports; nothing system-wide is used beyond the installed packages (Debian's
``slurm-wlm`` and ``munge``).

    reason = slurm_unavailable()          # None, or why a cluster cannot be made here
    with SlurmCluster() as cluster:       # started; the node is idle
        job = cluster.sbatch(["--array=0-1", script], env={**cluster.env, ...})
        cluster.tasks(job)                # {array task id: ArrayTask(state, exit_code)}
        cluster.scancel(f"{job}_0")       # SIGTERM to every process of the task, SIGKILL later
        cluster.signal_batch_shell(f"{job}_1", "TERM")  # to its batch shell alone
    # on exit: every job cancelled, stray job processes killed, daemons stopped, files removed

What works in a container without systemd or a writable cgroup tree (found on Debian 12,
slurm-wlm 22.05): ``ProctrackType=proctrack/linuxproc`` (a job's processes are found through their
parent pids, no cgroup), ``TaskPlugin=task/none`` and ``JobAcctGatherType=jobacct_gather/none``.
Then no plugin loads cgroup support, so no ``cgroup.conf`` is written; memory is scheduled
(``CR_Core_Memory``) but not enforced. The daemons run as root (``SlurmUser=root``), in the
foreground as children of the test, and are stopped by their pids. ``munged`` refuses a socket in
a directory that not everyone may search, so the directory is a ``mkdtemp`` opened to 0755, not
pytest's ``tmp_path`` (0700); slurm finds the socket through ``AuthInfo=socket=...``.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

from tests.support.net import free_port
from tests.support.waiting import wait_for

__all__ = ["ArrayTask", "SlurmCluster", "slurm_unavailable"]

DAEMONS = ("munged", "slurmctld", "slurmd")
CLIENTS = ("sbatch", "sinfo", "squeue", "scancel", "scontrol")
SBIN = ("/usr/sbin", "/usr/bin")
TERMINAL = {"COMPLETED", "FAILED", "CANCELLED", "TIMEOUT", "NODE_FAIL", "OUT_OF_MEMORY", "PREEMPTED",
            "BOOT_FAIL", "DEADLINE"}


def _which(name: str) -> str | None:
    return shutil.which(name) or next((f"{d}/{name}" for d in SBIN if os.access(f"{d}/{name}", os.X_OK)), None)


def slurm_unavailable() -> str | None:
    """None if a private cluster can run here, else why not."""
    missing = [n for n in (*DAEMONS, "munge", *CLIENTS) if _which(n) is None]
    if missing:
        return f"SLURM test needs {', '.join(missing)} (apt-get install -y slurm-wlm munge)"
    if os.geteuid() != 0:
        return "SLURM test needs root: slurmd starts job processes as the submitting user"
    return None


@dataclass(frozen=True)
class ArrayTask:
    """One array task as ``scontrol show job`` reports it."""

    state: str  # JobState: PENDING, RUNNING, COMPLETED, CANCELLED, FAILED, ...
    exit_code: str  # "status:signal", e.g. "0:0"

    @property
    def ended(self) -> bool:
        return self.state in TERMINAL


def node_line(node: str) -> str:
    """This machine's node description as ``slurmd -C`` detects it (CPUs, sockets, cores,
    threads, RealMemory in MB), named ``node`` and reached on 127.0.0.1."""
    out = subprocess.run([_which("slurmd"), "-C"], capture_output=True, text=True, timeout=60, check=True).stdout
    line = next(x for x in out.splitlines() if x.startswith("NodeName="))
    fields = [f for f in line.split()[1:] if not f.startswith("UpTime=")]
    return " ".join([f"NodeName={node}", "NodeAddr=127.0.0.1", *fields, "State=UNKNOWN"])


class SlurmCluster:
    """munged + slurmctld + slurmd of one node, all under ``self.root``."""

    def __init__(self) -> None:
        self.root = Path(tempfile.mkdtemp(prefix="bssrdf-slurm-"))
        self.root.chmod(0o755)  # munged: every directory above its socket must be searchable by all
        self.host = socket.gethostname().split(".")[0]  # slurmctld checks it is the SlurmctldHost
        self.conf = self.root / "slurm.conf"
        self.socket = self.root / "munge" / "munge.socket"
        self.procs: dict[str, subprocess.Popen] = {}
        self.jobs: list[str] = []

    @property
    def env(self) -> dict[str, str]:
        """The environment for SLURM's commands: this machine's, minus any SLURM_* of an enclosing
        allocation, plus SLURM_CONF naming this cluster's config."""
        env = {k: v for k, v in os.environ.items() if not k.startswith("SLURM_")}
        return {**env, "SLURM_CONF": str(self.conf)}

    def log(self, daemon: str) -> str:
        path = self.root / "log" / f"{daemon}.log"
        return path.read_text(errors="replace")[-3000:] if path.exists() else ""

    # --- start / stop ---
    def __enter__(self) -> SlurmCluster:
        try:
            self.start()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def start(self) -> None:
        for d in ("munge", "state", "spool", "log"):
            (self.root / d).mkdir(mode=0o755)
        key = self.root / "munge" / "munge.key"
        key.write_bytes(os.urandom(1024))
        key.chmod(0o400)
        self.conf.write_text(self._config())
        munge = self.root / "munge"
        self._start("munged", [_which("munged"), "-F", f"--socket={self.socket}", f"--key-file={key}",
                               f"--log-file={munge / 'munged.log'}", f"--pid-file={munge / 'munged.pid'}",
                               f"--seed-file={munge / 'munged.seed'}"])
        wait_for(lambda: self.socket.exists() or self._died("munged"), 30, "munged's socket")
        self._check_alive("munged")
        self._start("slurmctld", [_which("slurmctld"), "-D", "-c", "-i", "-f", str(self.conf)])
        self._start("slurmd", [_which("slurmd"), "-D", "-f", str(self.conf), "-N", self.host])
        try:
            wait_for(lambda: self._node_state() == "idle" or self._died("slurmctld") or self._died("slurmd"), 60,
                     "the node to be idle in sinfo")
        except AssertionError as exc:
            raise AssertionError(f"{exc}; slurmctld log: {self.log('slurmctld')}; slurmd log: {self.log('slurmd')}") from None
        for name in ("slurmctld", "slurmd"):
            self._check_alive(name)

    def _config(self) -> str:
        r = self.root
        return "\n".join([
            "ClusterName=bssrdftest",
            f"SlurmctldHost={self.host}(127.0.0.1)",
            f"SlurmctldPort={free_port()}",
            f"SlurmdPort={free_port()}",
            "SlurmUser=root",
            "SlurmdUser=root",
            "AuthType=auth/munge",
            "CredType=cred/munge",
            f"AuthInfo=socket={self.socket}",
            f"StateSaveLocation={r / 'state'}",
            f"SlurmdSpoolDir={r / 'spool'}",
            f"SlurmctldPidFile={r / 'slurmctld.pid'}",
            f"SlurmdPidFile={r / 'slurmd.pid'}",
            f"SlurmctldLogFile={r / 'log' / 'slurmctld.log'}",
            f"SlurmdLogFile={r / 'log' / 'slurmd.log'}",
            "ProctrackType=proctrack/linuxproc",
            "TaskPlugin=task/none",
            "JobAcctGatherType=jobacct_gather/none",
            "AccountingStorageType=accounting_storage/none",
            "SelectType=select/cons_tres",
            "SelectTypeParameters=CR_Core_Memory",
            "DefMemPerCPU=512",  # a job that asks for no memory does not take the whole node
            "SchedulerType=sched/backfill",
            "MpiDefault=none",
            "MailProg=/bin/true",
            "ReturnToService=2",
            node_line(self.host),
            f"PartitionName=test Nodes={self.host} Default=YES MaxTime=INFINITE State=UP",
            "",
        ])

    def _start(self, name: str, argv: list[str]) -> None:
        out = open(self.root / "log" / f"{name}.out", "wb")
        self.procs[name] = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, env=self.env,
                                            start_new_session=True)
        out.close()

    def _died(self, name: str) -> bool:
        proc = self.procs.get(name)
        return proc is None or proc.poll() is not None

    def _check_alive(self, name: str) -> None:
        if self._died(name):
            out = (self.root / "log" / f"{name}.out").read_text(errors="replace")[-2000:]
            raise RuntimeError(f"{name} exited with {self.procs[name].returncode}: {out} {self.log(name)}")

    def stop(self) -> None:
        """Cancel every job, wait (bounded) for their processes to go, kill any left, stop the
        daemons (slurmd and slurmctld before munged), remove the directory."""
        try:
            if self.jobs and not self._died("slurmctld"):
                self._run(["scancel", *self.jobs], check=False)
                try:
                    wait_for(lambda: not self._job_processes(), 45, "the jobs' processes to exit", poll=0.2)
                except AssertionError:
                    pass
            for pid in self._job_processes():  # SIGKILL after KillWait did not come: the daemons are ours to stop
                _kill(pid, signal.SIGKILL)
        finally:
            for name in ("slurmd", "slurmctld", "munged"):
                proc = self.procs.get(name)
                if proc is not None and proc.poll() is None:
                    proc.terminate()
                    try:
                        proc.wait(20)
                    except subprocess.TimeoutExpired:
                        proc.kill()
                        proc.wait(10)
            shutil.rmtree(self.root, ignore_errors=True)

    def _job_processes(self) -> list[int]:
        """Pids of the processes started for this cluster's jobs: their environment names this
        cluster's config (SLURM_CONF) and SLURM_JOB_ID; the daemons' own processes are excluded."""
        own = {p.pid for p in self.procs.values()}
        conf = f"SLURM_CONF={self.conf}".encode()
        pids = []
        for entry in Path("/proc").iterdir():
            if not entry.name.isdigit() or int(entry.name) in own:
                continue
            try:
                environ = (entry / "environ").read_bytes().split(b"\0")
            except OSError:
                continue
            if conf in environ and any(e.startswith(b"SLURM_JOB_ID=") for e in environ):
                pids.append(int(entry.name))
        return pids

    # --- commands ---
    def _run(self, argv: list[str], *, check: bool = True, env: dict | None = None) -> str:
        done = subprocess.run([_which(argv[0]), *argv[1:]], capture_output=True, text=True, timeout=60,
                              env=env or self.env)
        if check and done.returncode != 0:
            raise RuntimeError(f"{' '.join(argv)} exited {done.returncode}: {done.stderr.strip()}")
        return done.stdout

    def _node_state(self) -> str:
        return self._run(["sinfo", "-h", "-n", self.host, "-o", "%t"], check=False).strip()

    def sbatch(self, args: list[str], env: dict[str, str]) -> str:
        """Submit; returns the job id (for an array, the array's job id). ``env`` is the
        submitting shell's environment, which sbatch passes to the job (--export=ALL)."""
        job = self._run(["sbatch", "--parsable", *args], env=env).strip().split(";")[0]
        self.jobs.append(job)
        return job

    def scancel(self, target: str) -> None:
        self._run(["scancel", target])

    def signal_batch_shell(self, target: str, sig: str) -> None:
        """Signal the batch shell of ``target`` alone, not its children: what ``--signal=B:SIG@T``
        does T seconds before the time limit (``scancel --batch``)."""
        self._run(["scancel", "--batch", f"--signal={sig}", target])

    def tasks(self, job: str) -> dict[int, ArrayTask]:
        """The array tasks of ``job`` (a plain job is task 0): state and exit code. Finished jobs
        stay listed for MinJobAge (300 s by default)."""
        out = self._run(["scontrol", "-o", "show", "job", job])
        result = {}
        for line in out.splitlines():
            fields = dict(re.findall(r"(\w+)=(\S*)", line))
            if "JobState" in fields:
                task = fields.get("ArrayTaskId", "0")
                if task.isdigit():  # a pending remainder ("2-5") is not one task yet
                    result[int(task)] = ArrayTask(fields["JobState"], fields.get("ExitCode", ""))
        return result

    def wait_ended(self, job: str, count: int, timeout: float) -> dict[int, ArrayTask]:
        """Wait until ``count`` array tasks of ``job`` have all ended; their states."""
        def ended():
            tasks = self.tasks(job)
            return tasks if len(tasks) == count and all(t.ended for t in tasks.values()) else None

        return wait_for(ended, timeout, f"the {count} array tasks of job {job} to end", poll=0.5)


def _kill(pid: int, sig: int) -> None:
    try:
        os.kill(pid, sig)
    except ProcessLookupError:
        pass
