"""Offline stand-in for ansible-test's pip bootstrap script (get-pip.py).

ansible-test creates its virtual environments without pip and downloads a
get-pip-VERSION.py from Ansible's own CI file server to put pip in them; that
host cannot be reached from CI. tools/ansible-test copies this
file to ~/.ansible/test/cache/get_pip_VERSION.py, where ansible-test looks
first. Like the real script it runs pip from a wheel on sys.path, here the pip
wheel the interpreter carries for ensurepip (no download), and hands it the
arguments ansible-test gave: the `pip==VERSION` asked for then comes from PyPI.
"""

import glob
import os
import sys
import sysconfig


def pip_wheel():
    """The newest pip wheel of this interpreter's ensurepip: bundled, or where the distribution keeps it."""
    import ensurepip

    places = [os.path.join(os.path.dirname(ensurepip.__file__), "_bundled")]
    places.append(sysconfig.get_config_var("WHEEL_PKG_DIR") or "")
    places.append("/usr/share/python-wheels")  # Debian and Ubuntu's python3-venv
    wheels = [w for place in places if place for w in glob.glob(os.path.join(place, "pip-*.whl"))]
    if not wheels:
        sys.exit(f"get-pip (isaacsim.fleet): no pip wheel for ensurepip found for {sys.executable} in {places}")

    def version(path):
        return tuple(int(p) if p.isdigit() else 0 for p in os.path.basename(path).split("-")[1].split("."))

    return max(wheels, key=version)


def main():
    sys.path.insert(0, pip_wheel())
    # get-pip.py's own options; pip itself does not know them
    args = [a for a in sys.argv[1:] if a not in ("--no-setuptools", "--no-wheel")]
    from pip._internal.cli.main import main as pip_main

    sys.exit(pip_main(["install", "--upgrade", "--force-reinstall", *args]))


if __name__ == "__main__":
    main()
