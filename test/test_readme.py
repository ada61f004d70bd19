"""Every command in README.md's code blocks runs as typed (so README cannot rot).

Lines that install (``pip install``) or run the test suite are left out, as is a block marked
``<!-- readme-test: skip ... -->`` (it needs a ROS 2 install: docs/ros.md shows it run).
Long commands run in a quick form (QUICK: the README command -> what runs instead, from the
same command with arguments that make it short); every other command runs verbatim, in a
scratch directory holding ``bags/`` (a copy), ``benchmarks/`` and ``.venv`` (links), so
nothing in the repository is written.
"""

import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
VENV = Path(sys.prefix) if sys.prefix != sys.base_prefix else None   # the running venv

#: README command -> quick form (the command itself plus arguments that make it short)
QUICK = {
    ".venv/bin/lgs-wfs demo": ".venv/bin/lgs-wfs demo --frames 140 --full-frames 0 --algorithms cog",
    ".venv/bin/lgs-wfs reproduce --quick": None,   # minutes even quick: test_reproduce runs it
    ".venv/bin/lgs-wfs train ann_1k": ".venv/bin/lgs-wfs train ann_1k --quick --samples 3000 "
                                      "--out quick_models",
    ".venv/bin/python benchmarks/run.py": ".venv/bin/python benchmarks/run.py --quick "
                                          "--only turbulence --out quick_results.json",
}
#: exit codes other than 0 that a command gives by design (recover: 1 = something was cut)
EXIT = {".venv/bin/lgs-wfs recover damaged.mcap fixed.mcap": 1}
#: commands that run until interrupted: started, checked for this line, then SIGINT
SERVES = {"centroider_node": "centroider: cmf (start)"}


def readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    out, skip = [], False
    for block in re.finditer(r"(<!-- readme-test: skip[^>]*-->\s*)?```bash\n(.*?)```", text, re.S):
        if block.group(1):
            continue
        for line in block.group(2).splitlines():
            cmd = re.sub(r"\s+#.*$", "", line).strip()
            if not cmd or "pip install" in cmd or "pytest" in cmd:
                continue
            out.append(cmd)
    return out


def test_readme_has_the_commands_it_should():
    cmds = readme_commands()
    assert any(c.startswith(".venv/bin/lgs-wfs demo") for c in cmds)
    assert all(c.startswith(".venv/bin/") for c in cmds), [c for c in cmds if not c.startswith(".venv/bin/")]
    assert not any(c.startswith(("ros2 ", "colcon ", ". install")) for c in cmds)


@pytest.fixture(scope="module")
def scratch(tmp_path_factory):
    if VENV is None or not (VENV / "bin" / "lgs-wfs").exists():
        pytest.skip("needs the package installed in a venv (README's install line)")
    d = tmp_path_factory.mktemp("readme")
    shutil.copytree(ROOT / "bags", d / "bags", ignore=shutil.ignore_patterns("*_logs"))
    (d / "benchmarks").symlink_to(ROOT / "benchmarks")
    (d / ".venv").symlink_to(VENV)
    data = (d / "bags" / "sample.mcap").read_bytes()
    (d / "damaged.mcap").write_bytes(data[: len(data) * 2 // 3])      # a cut-off bag
    return d


@pytest.mark.slow
@pytest.mark.ros
@pytest.mark.parametrize("cmd", readme_commands())
def test_readme_command_runs(cmd, scratch):
    run = QUICK.get(cmd, cmd)
    if run is None:
        pytest.skip(f"{cmd!r}: run by another test (see QUICK)")
    assert run.startswith(cmd.split(" --")[0]), "a quick form must be the same command"
    env = dict(os.environ, PYTHONUNBUFFERED="1", MPLBACKEND="Agg")
    serves = next((line for name, line in SERVES.items() if name in run), None)
    if serves:
        proc = subprocess.Popen("exec " + run, shell=True, cwd=scratch, env=env, text=True,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                start_new_session=True)
        lines = []
        for line in proc.stdout:
            lines.append(line)
            if serves in line:
                break
        os.killpg(proc.pid, signal.SIGINT)
        rest, _ = proc.communicate(timeout=30)
        out = "".join(lines) + rest
        assert serves in out, out
        assert proc.returncode == 0 and "Traceback" not in out, out
        return
    proc = subprocess.run(run, shell=True, cwd=scratch, env=env, capture_output=True, text=True,
                          timeout=900)
    want = EXIT.get(cmd, 0)
    assert proc.returncode == want, f"{run}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    assert "Traceback" not in proc.stderr
