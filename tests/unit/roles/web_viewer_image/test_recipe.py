"""The web viewer recipe's own scripts, run as the image runs them (POSIX sh).

patch-runtime-config edits NVIDIA's scaffold at build time (the scaffold itself comes from
NVIDIA's npm registry and cannot be fetched here: the fixture is its one line the patch
needs); viewer-entrypoint writes the instance's settings when the container starts.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

FILES = Path(__file__).resolve().parents[4] / "roles" / "web_viewer_image" / "files"
# the lines of NVIDIA's sample app the patch relies on (create-ov-web-rtc-app 2.1.5, react)
MAIN = "const streamConfig = {\n    signalingServer: '127.0.0.1',\n    autoLaunch: true,\n};\n"
PAGE = (
    '<!doctype html>\n<html>\n  <head>\n    <script type="module" src="/src/main.tsx"></script>\n  </head>\n</html>\n'
)


def sh(script, *args, env=None, cwd=None):
    return subprocess.run(
        ["sh", str(FILES / script), *args], capture_output=True, text=True, env=env, cwd=cwd, check=False
    )


def test_the_patch_makes_the_page_read_its_address_and_ports_when_it_loads(tmp_path):
    (tmp_path / "main.tsx").write_text(MAIN)
    (tmp_path / "index.html").write_text(PAGE)
    result = sh("patch-runtime-config", "main.tsx", "index.html", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    main = (tmp_path / "main.tsx").read_text()
    assert "'127.0.0.1'" not in main
    # the signalling's address and scheme apart from the media's (stream-config.js sets them)
    assert "signalingServer: (window as any).ISAACSIM_STREAM.signalHost," in main
    assert "mediaServer: (window as any).ISAACSIM_STREAM.host," in main
    assert "signalingPort: (window as any).ISAACSIM_STREAM.signalPort," in main
    assert "mediaPort: (window as any).ISAACSIM_STREAM.streamPort," in main
    assert "forceWSS: (window as any).ISAACSIM_STREAM.wss," in main and "autoLaunch: true," in main
    page = (tmp_path / "index.html").read_text().splitlines()
    config = page.index('    <script src="/stream-config.js"></script>')
    assert config < next(n for n, line in enumerate(page) if 'type="module"' in line)


def test_the_patch_fails_loudly_when_the_scaffold_changed(tmp_path):
    (tmp_path / "main.tsx").write_text("const streamConfig = { server: 'x' };\n")
    (tmp_path / "index.html").write_text(PAGE)
    result = sh("patch-runtime-config", "main.tsx", "index.html", cwd=tmp_path)
    assert result.returncode == 1 and "the scaffold changed" in result.stderr


def viewer_env(root, **over):
    env = {
        "PATH": "/usr/bin:/bin",
        "VIEWER_ROOT": str(root),
        "ISAACSIM_HOST": "10.1.2.3",
        "ISAACSIM_SIGNAL_PORT": "49101",
        "ISAACSIM_STREAM_PORT": "47999",
        "WEB_VIEWER_PORT": "8211",
    }
    env.update(over)
    return env


def test_the_entrypoint_writes_the_settings_then_runs_the_server(tmp_path):
    result = sh("viewer-entrypoint", "echo", "server started", env=viewer_env(tmp_path))
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[-1] == "server started"
    config = (tmp_path / "stream-config.js").read_text().splitlines()
    assert config[0] == 'window.ISAACSIM_STREAM = {"host": "10.1.2.3", "signalPort": 49101, "streamPort": 47999};'
    # over HTTPS (the front door), the signalling goes back to the page's origin over WSS (a
    # browser runs it: tests/integration/instances/test_web_viewer_front_door.py)
    assert '  s.wss = location.protocol === "https:";' in config
    assert "  s.signalHost = s.wss ? location.hostname : s.host;" in config


@pytest.mark.parametrize(
    "over, words",
    [
        ({"ISAACSIM_HOST": "0.0.0.0"}, "not an address a browser can reach"),
        ({"ISAACSIM_HOST": ""}, "not an address a browser can reach"),
        ({"ISAACSIM_HOST": "localhost"}, "not an address a browser can reach"),
        ({"ISAACSIM_HOST": "10.0.0.300"}, "is not an IPv4 address"),
        ({"ISAACSIM_HOST": "239.1.1.1"}, "not a unicast address"),
        ({"ISAACSIM_HOST": 'x";alert(1);"'}, "neither an IPv4 address nor a host name"),
        ({"ISAACSIM_SIGNAL_PORT": "70000"}, "ISAACSIM_SIGNAL_PORT '70000' is not a port number"),
        ({"WEB_VIEWER_PORT": "80a"}, "WEB_VIEWER_PORT '80a' is not a port number"),
    ],
)
def test_the_entrypoint_refuses_what_a_browser_could_not_use(tmp_path, over, words):
    result = sh("viewer-entrypoint", "echo", "server started", env=viewer_env(tmp_path, **over))
    assert result.returncode == 2 and words in result.stderr
    assert "server started" not in result.stdout and not (tmp_path / "stream-config.js").exists()
