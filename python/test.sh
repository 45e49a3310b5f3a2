#!/usr/bin/env bash
# The Python module's tests, from a machine with only the Rust toolchain and Python 3: installs
# OSMesa (MuJoCo's off-screen renderer) from Debian if it is missing, builds and installs the
# module with Meta-World into a virtual environment, and runs pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! ldconfig -p | grep -q 'libOSMesa\.so'; then
  sudo=""
  [ "$(id -u)" = 0 ] || sudo=sudo
  $sudo apt-get update -qq
  $sudo apt-get install -y -qq libosmesa6 >/dev/null
fi
venv=${SCDP_VENV:-.venv-python}
[ -x "$venv/bin/python" ] || python3 -m venv "$venv"
"$venv/bin/pip" install -q --upgrade pip
"$venv/bin/pip" install -q './python[metaworld,test]'
MUJOCO_GL=osmesa "$venv/bin/python" -m pytest -q -p no:cacheprovider python/tests "$@"
