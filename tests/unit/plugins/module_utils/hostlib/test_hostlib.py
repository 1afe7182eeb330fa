"""plugins/module_utils/hostlib is the library the role copies, whole and flat, to every host for
the status endpoint and the metrics exporter (roles/isaac_sim/vars/main.yml lists the directory).
On a host there is no collection: each file imports only the standard library and the other
files of the directory, by their bare names."""

import ast
import subprocess
import sys
from pathlib import Path

import pytest

HOSTLIB = Path(__file__).resolve().parents[5] / "plugins" / "module_utils" / "hostlib"
FILES = sorted(p for p in HOSTLIB.glob("*.py") if p.name != "__init__.py")
NAMES = {p.stem for p in FILES}
COLLECTION = "ansible_collections.isaacsim.fleet.plugins.module_utils"
# NVIDIA's NVML binding: imported only when a caller asks for NVML (gpu_usage falls back to nvidia-smi)
OPTIONAL = {"pynvml"}


def imports(path: Path):
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            yield node.module
            yield from (f"{node.module}.{alias.name}" for alias in node.names if node.module == COLLECTION)


@pytest.mark.parametrize("path", FILES, ids=lambda p: p.name)
def test_a_host_library_file_imports_only_the_standard_library_and_its_directory(path):
    outside = []
    for name in imports(path):
        top = name.split(".")[0]
        if name.startswith(COLLECTION + ".hostlib") or top in NAMES | OPTIONAL or top == "__future__":
            continue
        if name.startswith("ansible") or top not in sys.stdlib_module_names:
            outside.append(name)
    assert outside == [], f"{path.name} imports {outside}: a host has only plugins/module_utils/hostlib"


def test_the_library_copied_flat_imports_on_its_own(tmp_path):
    for path in FILES:
        (tmp_path / path.name).write_text(path.read_text())
    code = "import sys; sys.path.insert(0, '.'); import " + ", ".join(sorted(NAMES))
    # -I: no site packages, no collection on the path, as on a host with a bare Python; the
    # directory first on the path, as the host's scripts put it
    run = subprocess.run([sys.executable, "-I", "-c", code], cwd=tmp_path, capture_output=True, text=True, check=False)
    assert run.returncode == 0, run.stderr
