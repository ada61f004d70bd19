"""Start a graph of nodes as separate processes, without the ros2 CLI or launch.

What ``launch/demo.launch.py`` does on a ROS install, for a plain venv: each node is
``python -m lgs_wfs_ros.ros.<node> --ros-args -r __ns:=/<ns> --params-file <yaml> -r a:=b``.
Processes share the caller's environment (ROS_DOMAIN_ID, discovery range, DDS profile).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from . import environment


@dataclass
class NodeSpec:
    """One node process: module under lgs_wfs_ros.ros, namespace, parameters, remappings."""
    node: str
    namespace: str = "wfs"
    params: dict = field(default_factory=dict)
    remaps: dict = field(default_factory=dict)

    def command(self, workdir: Path) -> list[str]:
        params_file = workdir / f"{self.namespace}_{self.node}.yaml"
        # JSON is YAML: no extra dependency, and strings with ':' or '{' stay strings.
        params_file.write_text(json.dumps({"/**": {"ros__parameters": self.params}}))
        cmd = [sys.executable, "-m", f"lgs_wfs_ros.ros.{self.node}", "--ros-args",
               "-r", f"__ns:=/{self.namespace}", "--params-file", str(params_file)]
        for src, dst in self.remaps.items():
            cmd += ["-r", f"{src}:={dst}"]
        return cmd


class Graph:
    """Processes of a node graph; a context manager that interrupts them all on exit."""

    def __init__(self, specs: list[NodeSpec], log_dir: str | Path | None = None):
        self.specs = specs
        self._tmp = tempfile.TemporaryDirectory(prefix="lgs_wfs_graph_")
        self.workdir = Path(self._tmp.name)
        self.log_dir = Path(log_dir) if log_dir else self.workdir
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.procs: dict[str, subprocess.Popen] = {}

    def __enter__(self):
        env = dict(os.environ)
        environment.configure(env)
        env.setdefault("PYTHONUNBUFFERED", "1")
        for spec in self.specs:
            key = f"{spec.namespace}/{spec.node}"
            log = open(self.log_dir / f"{spec.namespace}_{spec.node}.log", "w")
            self.procs[key] = subprocess.Popen(spec.command(self.workdir), env=env, stdout=log,
                                               stderr=subprocess.STDOUT)
            log.close()
        return self

    def wait(self, key: str, timeout: float) -> int | None:
        """Wait for one process to exit; its return code, or None on timeout."""
        try:
            return self.procs[key].wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            return None

    def log(self, key: str) -> str:
        ns, node = key.split("/")
        path = self.log_dir / f"{ns}_{node}.log"
        return path.read_text() if path.exists() else ""

    def stop(self, timeout: float = 10.0) -> dict[str, int]:
        """SIGINT every process still running, then SIGKILL what did not exit in time."""
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
        deadline = time.monotonic() + timeout
        codes = {}
        for key, proc in self.procs.items():
            try:
                codes[key] = proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                proc.kill()
                codes[key] = proc.wait()
        return codes

    def __exit__(self, *exc):
        self.stop()
        self._tmp.cleanup()
