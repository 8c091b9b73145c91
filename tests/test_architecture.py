"""The import rule of ARCHITECTURE.md, enforced by reading every module's imports.

cdpr <- drivers <- sim_bus <- tuning; in daemon/, the service uses only cdpr, drivers and
the config; the zenoh interface only cdpr, the config and the service's command
contract; the service process everything but the command line; the command line and
bench/ may use everything.  No two modules import each other, directly or round a circle.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent

#: package -> the packages (prefixes of module names) it may import
ALLOWED: dict[str, tuple[str, ...]] = {
    "daemon": (),  # only its subpackages hold code
    "cdpr": ("cdpr",),
    "drivers": ("cdpr", "drivers"),
    "sim_bus": ("cdpr", "drivers", "sim_bus"),
    "tuning": ("cdpr", "drivers", "sim_bus", "tuning"),
    "daemon.config": ("cdpr", "drivers", "daemon.config"),
    "daemon.service": ("cdpr", "drivers", "daemon.config", "daemon.service"),
    "daemon.interface": ("cdpr", "daemon.config", "daemon.service.api", "daemon.interface"),
    "daemon.process": ("cdpr", "drivers", "daemon.config", "daemon.service", "daemon.interface",
                       "daemon.process"),
    "daemon.cli": ("cdpr", "drivers", "sim_bus", "tuning", "daemon"),
}
PROJECT = ("cdpr", "drivers", "sim_bus", "tuning", "daemon")


def module_name(path: Path, root: Path) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports(
    path: Path, root: Path, *, runtime_only: bool = False
) -> Iterator[tuple[str, ...]]:
    """What `path` imports from the project, one tuple per imported name: the names it
    may be (`from pkg import x` is the module pkg.x or a name in pkg), the most specific
    first; relative imports resolved.  Imports under `if TYPE_CHECKING:` are skipped when
    `runtime_only` (they never run)."""
    tree = ast.parse(path.read_text(), str(path))
    package = module_name(path, root)
    if path.name != "__init__.py":
        package = package.rpartition(".")[0]
    skipped = set()
    if runtime_only:
        for node in ast.walk(tree):
            if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
                skipped.update(id(n) for stmt in node.body for n in ast.walk(stmt))
    for node in ast.walk(tree):
        if id(node) in skipped:
            continue
        if isinstance(node, ast.Import):
            found = [(alias.name,) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                anchor = ".".join(parts[: len(parts) - node.level + 1])
                base = ".".join(p for p in (anchor, base) if p)
            found = [(f"{base}.{alias.name}".lstrip("."), base) for alias in node.names]
        else:
            continue
        for names in found:
            if names[0].split(".")[0] in PROJECT:
                yield names


def home(module: str) -> str | None:
    """The ALLOWED key a module belongs to (the longest matching prefix)."""
    keys = [k for k in ALLOWED if module == k or module.startswith(k + ".")]
    return max(keys, key=len) if keys else None


def within(module: str, prefixes: tuple[str, ...]) -> bool:
    return any(module == p or module.startswith(p + ".") for p in prefixes)


def violations(root: Path) -> list[str]:
    """Every import that breaks ALLOWED, as 'file: imports module'."""
    found = []
    for path in sorted(root.glob("*/**/*.py")):
        if path.relative_to(root).parts[0] not in PROJECT:
            continue
        owner = home(module_name(path, root))
        if owner is None:
            found.append(f"{path.relative_to(root)}: in no package of the import rule")
            continue
        for names in imports(path, root):
            if not any(within(name, ALLOWED[owner]) for name in names):
                found.append(f"{path.relative_to(root)}: imports {names[0]} ({owner} may not)")
    return found


def cycles(root: Path) -> list[list[str]]:
    """Circles of imports between project modules, deferred ones (inside a function)
    included: a circle broken only by deferring an import is still a circle."""
    modules = {
        module_name(p, root): p
        for p in root.glob("*/**/*.py")
        if p.relative_to(root).parts[0] in PROJECT
    }
    graph = {
        name: {
            next((m for m in names if m in modules), "")
            for names in imports(path, root, runtime_only=True)
        }
        - {"", name}
        for name, path in modules.items()
    }
    found, state = [], dict.fromkeys(graph, 0)  # 0 new, 1 on the stack, 2 done

    def visit(name: str, stack: list[str]) -> None:
        state[name] = 1
        for nxt in sorted(graph[name]):
            if state[nxt] == 1:
                found.append([*stack[stack.index(nxt):], nxt])
            elif state[nxt] == 0:
                visit(nxt, [*stack, nxt])
        state[name] = 2

    for name in sorted(graph):
        if state[name] == 0:
            visit(name, [name])
    return found


def test_the_project_keeps_the_import_rule() -> None:
    assert violations(ROOT) == []


def test_no_import_circles() -> None:
    assert cycles(ROOT) == []


def test_every_package_has_a_rule() -> None:
    packages = {p.parent.name for p in ROOT.glob("*/__init__.py")} & set(PROJECT)
    assert packages == set(PROJECT)
    daemon_parts = {p.parent.name for p in (ROOT / "daemon").glob("*/__init__.py")}
    assert {f"daemon.{d}" for d in daemon_parts} <= set(ALLOWED)


def _tree(tmp_path: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        path = tmp_path / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return tmp_path


@pytest.mark.parametrize(
    ("module", "source", "culprit"),
    [
        ("cdpr/model.py", "import drivers.base\n", "drivers.base"),
        ("cdpr/model.py", "from daemon.config import load_config\n", "daemon.config"),
        ("sim_bus/runner.py", "from tuning import rig\n", "tuning.rig"),
        ("daemon/service/service.py", "from daemon.interface import zenoh_io\n", "zenoh_io"),
        ("daemon/service/service.py", "def f():\n    import sim_bus.runner\n", "sim_bus"),
        ("daemon/interface/zenoh_io.py", "from ..service import safety\n", "safety"),
        ("drivers/base.py", "from .. import sim_bus\n", "sim_bus"),
    ],
)
def test_a_forbidden_import_is_found(
    tmp_path: Path, module: str, source: str, culprit: str
) -> None:
    root = _tree(tmp_path, {module: source})
    found = violations(root)
    assert len(found) == 1 and culprit in found[0] and module in found[0]


def test_allowed_imports_pass(tmp_path: Path) -> None:
    root = _tree(
        tmp_path,
        {
            "daemon/cli/run_cmd.py": "import tuning.rig\nfrom sim_bus import runner\n",
            "daemon/service/service.py": "from daemon.config import DaemonConfig\n",
            "daemon/interface/zenoh_io.py": "from daemon.service.api import CommandError\n",
            "tuning/rig.py": "from sim_bus.plant import Plant\n",
        },
    )
    assert violations(root) == []


def test_a_circle_is_found(tmp_path: Path) -> None:
    root = _tree(
        tmp_path,
        {
            "sim_bus/plant/a.py": "from sim_bus.plant.b import B\n",
            "sim_bus/plant/b.py": "def f():\n    pass\nfrom sim_bus.plant import a\n",
            "sim_bus/plant/c.py": "def g():\n    from sim_bus.plant import d\n",
            "sim_bus/plant/d.py": "import typing\nif typing.TYPE_CHECKING:\n    import c\n"
            "from sim_bus.plant import c\n",
            "sim_bus/plant/e.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
            "    from sim_bus.plant.f import F\n",
            "sim_bus/plant/f.py": "from sim_bus.plant.e import E\n",  # e -> f for types only
        },
    )
    assert cycles(root) == [
        ["sim_bus.plant.a", "sim_bus.plant.b", "sim_bus.plant.a"],
        ["sim_bus.plant.c", "sim_bus.plant.d", "sim_bus.plant.c"],
    ]


def test_the_documented_folder_map_matches_the_tree() -> None:
    """Every package folder appears in the architecture page's map, and every folder the
    map names exists."""
    text = (ROOT / "docs" / "explanation" / "architecture.md").read_text()
    block = text[text.index("```") + 3 :]
    block = block[: block.index("```")]
    named, parents = set(), []
    for line in block.splitlines():
        stripped = line.lstrip()
        if not stripped or not stripped.split()[0].endswith("/"):
            continue
        depth = (len(line) - len(stripped)) // 2
        parents[depth:] = [stripped.split()[0].rstrip("/")]
        named.add("/".join(parents))
    packages = {
        str(p.parent.relative_to(ROOT))
        for top in PROJECT
        for p in (ROOT / top).glob("**/__init__.py")
    }
    assert packages <= named, f"missing from the map: {sorted(packages - named)}"
    assert all((ROOT / folder).is_dir() for folder in named), sorted(
        f for f in named if not (ROOT / f).is_dir()
    )


def _signatures_added(setup: str, action: str) -> str:
    """Run `setup`, then `action`, in a fresh interpreter (nothing else warmed the
    kernels): "True {...}", the kernels of cdpr and sim_bus that gained a compiled
    signature in `action` (True: setup loaded some)."""
    import subprocess
    import sys

    probe = (
        "import sys\n"
        "from numba.core.registry import CPUDispatcher\n"
        "def compiled():\n"
        "    return {(m.__name__, name): len(f.signatures) for m in list(sys.modules.values())\n"
        "            if (m.__name__ or '').startswith(('cdpr', 'sim_bus'))\n"
        "            for name, f in vars(m).items() if isinstance(f, CPUDispatcher)}\n"
        f"{setup}"
        "before = compiled()\n"
        f"{action}"
        "after = compiled()\n"
        "print(sum(before.values()) > 0, {k: v for k, v in after.items() if before.get(k) != v})\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, check=False
    )
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


def test_the_real_time_core_compiles_nothing_once_its_robot_is_built() -> None:
    """The core's kernels (kinematics, forward kinematics, the model terms) are loaded
    when its robot is built (Robot._load_kernels): a goto flown lock-step after that,
    with the simulator's plant, adds no compiled signature to any kernel, so no cycle
    waits on numba."""
    setup = (
        "import numpy as np\n"
        "from cdpr import Pose\n"
        "from cdpr.controller import ParallelController\n"
        "from cdpr.trajectory import Reference, TrajectoryLimits, goto\n"
        "from sim_bus.plant import Plant, equilibrium_tensions\n"
        "from tests.conftest import load_robot\n"
        "from tuning.lockstep import run_lockstep\n"
        "robot = load_robot('reference8')\n"
        "home = robot.home\n"
        "plant = Plant(robot)\n"
        "plant.reset(home, equilibrium_tensions(robot, home))\n"
        "controller = ParallelController(robot)\n"
        "controller.reset(home)\n"
        "target = Pose(home.position + np.array([0.1, 0.0, 0.05]), home.quaternion)\n"
        "rest = Reference(home, np.zeros(6), np.zeros(6))\n"
        "controller.follow(goto(rest, target, TrajectoryLimits()))\n"
    )
    action = "run_lockstep(plant, lambda t, l, r: controller.step(t, l, r).commands, 0.3, 500)\n"
    assert _signatures_added(setup, action) == "True {}"


def test_the_trusted_lengths_check_compiles_nothing_in_a_cycle() -> None:
    """The consistency check's null-space kernel is loaded when the check is built: its
    linearisation at a pose, which a cycle runs as the platform moves, adds no compiled
    signature."""
    setup = (
        "from daemon.service.trusted_lengths import TrustedLengths\n"
        "from tests.conftest import load_robot\n"
        "robot = load_robot('reference8')\n"
        "trust = TrustedLengths(robot, list(range(1, 9)), max_speed=3.0, tolerance=1e-3,\n"
        "                       slack=0.01, rest_tensions=[100.0] * 8)\n"
    )
    assert _signatures_added(setup, "trust.follow_pose(robot.home)\n") == "True {}"


def test_the_companion_compiles_nothing_for_a_client_s_trajectory() -> None:
    """The companion loads the validation's kernels before the core's hang timer runs
    (planner.load_checks, from a trajectory of Waypoints); a client's trajectory, parsed
    from its interface form as zenoh hands it over (arrays, read-only knots) and
    validated as the daemon validates one, adds no compiled signature: numba compiling
    a new array type there took the companion's event loop seconds on a slow host
    (the UML guest: killed as silent).  With rates given at one waypoint the parser
    takes the Waypoint path; it adds none either."""
    setup = (
        "from daemon.config import load_config\n"
        "from daemon.service.planner import load_checks, validate_as_the_daemon\n"
        "from cdpr.trajectory.parse import parse_trajectory\n"
        "from tests.processes import CONFIG\n"
        "config = load_config(CONFIG)\n"
        "load_checks(config)\n"
        "x, y, z = config.robot.home.position.tolist()\n"
        "def point(t, dx, **rates):\n"
        "    return {'t': t, 'position': [x + dx, y, z],\n"
        "            'quaternion': {'w': 1.0, 'x': 0.0, 'y': 0.0, 'z': 0.0}, **rates}\n"
        "plain = [point(0.0, 0.0), point(1.0, 0.03), point(2.0, 0.05)]\n"
        "still = {'linear': [0, 0, 0], 'angular': [0, 0, 0]}\n"
        "rated = [point(0.0, 0.0, twist=still), point(2.0, -0.04)]\n"
    )
    action = (
        "for waypoints in (plain, rated):\n"
        "    validate_as_the_daemon(parse_trajectory({'waypoints': waypoints}), config)\n"
    )
    assert _signatures_added(setup, action) == "True {}"
