"""The package stays a valid ament_python package: package.xml, colcon build, lib/<pkg> executables."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NODES = ("simulator_node", "centroider_node", "recorder_node", "player_node")


def test_package_xml_is_valid_format_3():
    catkin_pkg = pytest.importorskip("catkin_pkg.package", reason="catkin_pkg comes with colcon-ros")
    pkg = catkin_pkg.parse_package(str(ROOT / "package.xml"))
    pkg.validate()
    assert pkg.package_format == 3 and pkg.name == "lgs_wfs_ros"
    assert pkg.get_build_type() == "ament_python"
    assert all("@" in m.email and "." in m.email.split("@")[1] for m in pkg.maintainers)
    deps = {d.name for d in pkg.exec_depends}
    assert {"rclpy", "std_msgs", "sensor_msgs"} <= deps
    assert (ROOT / "resource" / "lgs_wfs_ros").is_file()


@pytest.mark.slow
def test_colcon_build_installs_ros2_run_executables(tmp_path):
    colcon = shutil.which("colcon") or str(Path(sys.executable).parent / "colcon")
    if not Path(colcon).exists():
        pytest.skip("colcon is not installed (pip install '.[test]' brings it)")
    src = tmp_path / "src" / "lgs_wfs_ros"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(".git", ".venv", "build", "install",
                                                             "log", "*.mcap", "__pycache__"))
    proc = subprocess.run([colcon, "build", "--packages-select", "lgs_wfs_ros"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    prefix = tmp_path / "install" / "lgs_wfs_ros"
    lib = prefix / "lib" / "lgs_wfs_ros"
    for node in NODES:
        assert (lib / node).is_file(), f"ros2 run would not find {node}"
    share = prefix / "share"
    assert (share / "ament_index" / "resource_index" / "packages" / "lgs_wfs_ros").is_file()
    assert (share / "lgs_wfs_ros" / "package.xml").is_file()
    assert (share / "lgs_wfs_ros" / "launch" / "demo.launch.py").is_file()
    # what `ros2 run lgs_wfs_ros centroider_node` executes, with a parameter it must refuse
    site = next(prefix.glob("lib/python3*/site-packages"))
    env = dict(os.environ, PYTHONPATH=str(site))
    run = subprocess.run([sys.executable, str(lib / "centroider_node"), "--ros-args",
                          "-p", "algorithm:=bogus"], capture_output=True, text=True, timeout=60, env=env)
    assert run.returncode != 0
    assert "bogus" in (run.stdout + run.stderr)


# -- dependencies: declared where they are used ------------------------------------------------
import ast  # noqa: E402
import importlib.metadata as md  # noqa: E402
import re  # noqa: E402

PKG = ROOT / "lgs_wfs_ros"
#: top-level modules the `ros` extra's wheels provide (ros/ only)
ROS_MODULES = {"rclpy", "rcl_interfaces", "std_msgs", "sensor_msgs", "builtin_interfaces"}
#: test-only tools: never imported by the package
TEST_ONLY = {"aotools", "mcap_ros2", "pytest"}


def _setup_requirements() -> dict:
    """``{"install_requires": [...], extra: [...]}`` read from setup.py (names only, lower case)."""
    tree = ast.parse((ROOT / "setup.py").read_text())
    call = next(n for n in ast.walk(tree) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "setup")
    kw = {k.arg: ast.literal_eval(k.value) for k in call.keywords if k.arg in ("install_requires", "extras_require")}
    name = lambda req: re.split(r"[<>=!\[; ]", req, maxsplit=1)[0].lower().replace("_", "-")  # noqa: E731
    out = {"install_requires": [name(r) for r in kw["install_requires"]]}
    out.update({k: [name(r) for r in v] for k, v in kw["extras_require"].items()})
    return out


def _third_party_imports(path: Path):
    """``(top-level module, lazy, guarded)`` of every import of a non-stdlib module in a file.

    lazy: inside a function; guarded: inside a ``try`` that catches ImportError/Exception."""
    tree = ast.parse(path.read_text())
    out = []

    def visit(node, lazy, guarded):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.Import):
                mods = [a.name for a in child.names]
            elif isinstance(child, ast.ImportFrom) and child.level == 0:
                mods = [child.module]
            else:
                mods = []
            for m in mods:
                top = m.split(".")[0]
                if top not in sys.stdlib_module_names and top != "lgs_wfs_ros":
                    out.append((top, lazy, guarded))
            g = guarded or (isinstance(child, ast.Try) and any(
                h.type is None or getattr(h.type, "id", "") in ("ImportError", "ModuleNotFoundError", "Exception")
                for h in child.handlers))
            visit(child, lazy or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)), g)
    visit(tree, False, False)
    return out


def test_every_import_is_declared_in_the_right_extra():
    """Runtime modules import only install_requires (or guard the import); ros/ may add the
    `ros` extra's modules; torch only lazily and from the `train` extra; the test-only tools
    (aotools, mcap-ros2-support) are never imported by the package and live in `test`; the
    mcap container library is runtime (bags/reader.py reads through it)."""
    req = _setup_requirements()
    dists = md.packages_distributions()
    runtime = set(req["install_requires"])
    assert {"aotools", "mcap-ros2-support", "setuptools"}.isdisjoint(runtime)
    assert "mcap" in runtime
    assert {"aotools", "mcap-ros2-support", "pytest"} <= set(req["test"])
    assert any(r.startswith("torch") for r in req["train"])
    problems = []
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(ROOT).as_posix()
        for top, lazy, guarded in _third_party_imports(path):
            names = {d.lower().replace("_", "-") for d in dists.get(top, [top])}
            if top in TEST_ONLY:
                problems.append(f"{rel}: imports the test-only {top}")
            elif guarded or names & runtime:
                continue
            elif top == "torch" and lazy and "/learning/" in rel:
                continue
            elif top in ROS_MODULES and "/ros/" in rel:
                continue
            else:
                problems.append(f"{rel}: imports {top} ({', '.join(sorted(names))}), not in install_requires")
    assert not problems, "\n".join(problems)


def _runtime_venv(tmp_path) -> Path:
    """A fresh venv with the package and its install_requires only (versions from
    constraints.txt), built from a copy of the source tree; returns its python."""
    src = tmp_path / "src"
    shutil.copytree(ROOT, src, ignore=shutil.ignore_patterns(".git", ".venv", "build", "install", "log",
                                                             "*.mcap", "__pycache__", "*.egg-info"))
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    py = venv / "bin" / "python"
    pip = subprocess.run([str(py), "-m", "pip", "install", "-q", "-c", str(ROOT / "constraints.txt"), str(src)],
                         capture_output=True, text=True, timeout=900)
    assert pip.returncode == 0, pip.stderr[-3000:]
    return py


@pytest.mark.slow
def test_runtime_venv_imports_every_module_and_pip_check_is_clean(tmp_path):
    """With only install_requires: pip check is clean, every module outside ros/ imports,
    and a ros/ module fails only for want of the `ros` extra's modules; the `train` verb
    names its extra."""
    py = _runtime_venv(tmp_path)
    check = subprocess.run([str(py), "-m", "pip", "check"], capture_output=True, text=True, timeout=300)
    assert check.returncode == 0, check.stdout + check.stderr
    code = ("import importlib, pkgutil, json, lgs_wfs_ros\n"
            "out = {}\n"
            "for m in pkgutil.walk_packages(lgs_wfs_ros.__path__, 'lgs_wfs_ros.'):\n"
            "    try:\n"
            "        importlib.import_module(m.name); out[m.name] = None\n"
            "    except ImportError as e:\n"
            "        out[m.name] = getattr(e, 'name', None) or str(e)\n"
            "print(json.dumps(out))")
    run = subprocess.run([str(py), "-c", code], capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    import json
    result = json.loads(run.stdout)
    assert len(result) > 40
    for mod, missing in result.items():
        if ".ros." in mod:
            assert missing is None or missing.split(".")[0] in ROS_MODULES, (mod, missing)
        else:
            assert missing is None, (mod, missing)
    train = subprocess.run([str(py), "-m", "lgs_wfs_ros.cli", "train", "ann_1k", "--out", str(tmp_path / "m")],
                           capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert train.returncode == 2 and "'train' extra" in train.stderr and "Traceback" not in train.stderr


def test_import_contracts_hold(tmp_path, monkeypatch):
    """import-linter (setup.cfg): the layers sensor -> optics -> bags -> centroiding ->
    learning -> analysis -> ros -> cli (a lower one never imports a higher one) and no
    import cycle between sibling modules anywhere in the package."""
    from importlinter.cli import lint_imports
    monkeypatch.chdir(ROOT)
    assert lint_imports(config_filename=str(ROOT / "setup.cfg"), no_cache=True, no_logo=True) == 0
