#!/usr/bin/env bash
# System libraries flowerpose needs beyond Python packages: libusb-1.0 (open3d loads it) and
# Mesa's EGL with its software rasteriser (headless rendering for MuJoCo and pyrender); for
# the tests, mosquitto and openssl (the cloud backend's tests run a real MQTT broker, plain
# and with a test certificate) and Chromium (report.html is checked in a headless browser).
set -euo pipefail
missing=()
# Read the library list once: `ldconfig -p | grep -q` fails under pipefail when grep stops
# early and ldconfig gets SIGPIPE.
libs=$(ldconfig -p 2>/dev/null || true)
has() { grep -qF "$1" <<<"$libs"; }
has 'libusb-1.0.so.0' || missing+=(libusb-1.0-0)
has 'libEGL.so.1' || missing+=(libegl1)
has 'libEGL_mesa.so.0' || missing+=(libegl-mesa0)
has 'libgbm.so.1' || missing+=(libgbm1)
compgen -G "/usr/lib/*/dri/swrast_dri.so" >/dev/null || missing+=(libgl1-mesa-dri)
command -v mosquitto >/dev/null || [ -x /usr/sbin/mosquitto ] || missing+=(mosquitto)
command -v openssl >/dev/null || missing+=(openssl)
command -v chromium >/dev/null || missing+=(chromium)
[ ${#missing[@]} -eq 0 ] && exit 0
echo "installing system packages: ${missing[*]}"
if [ "$(id -u)" -eq 0 ]; then sudo=""; elif command -v sudo >/dev/null; then sudo="sudo"; else
  echo "error: need root or sudo to install ${missing[*]} (apt-get install ${missing[*]})" >&2
  exit 2
fi
export DEBIAN_FRONTEND=noninteractive
$sudo apt-get install -y -q "${missing[@]}" >/dev/null 2>&1 || {
  $sudo apt-get update -q >/dev/null && $sudo apt-get install -y -q "${missing[@]}" >/dev/null; }
