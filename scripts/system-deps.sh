#!/usr/bin/env bash
# Installs the shared libraries bgs-batch loads at run time and pip cannot provide: Open3D needs
# libusb-1.0, Open3D and PyTorch the OpenMP runtime. `make demo`, `make test` and `.ci/run` call
# this first. Silent when all are present; as root it installs the missing ones with apt-get,
# otherwise it names the command to run and exits 1.
set -euo pipefail

# soname                package (Debian/Ubuntu)
LIBRARIES="
libusb-1.0.so.0         libusb-1.0-0
libgomp.so.1            libgomp1
"

ldconfig_cmd=ldconfig
command -v ldconfig >/dev/null 2>&1 || ldconfig_cmd=/sbin/ldconfig
known=$("$ldconfig_cmd" -p 2>/dev/null || true)

missing=() packages=()
while read -r soname package; do
    [ -n "$soname" ] || continue
    if ! grep -qF "$soname " <<<"$known"; then
        missing+=("$soname")
        packages+=("$package")
    fi
done <<<"$LIBRARIES"
[ ${#missing[@]} -eq 0 ] && exit 0

if [ "$(id -u)" != 0 ]; then
    echo "system-deps: missing ${missing[*]}; run: sudo apt-get install -y ${packages[*]}" >&2
    exit 1
fi
log=$(mktemp)
trap 'rm -f "$log"' EXIT
if ! { apt-get update -qq && DEBIAN_FRONTEND=noninteractive \
        apt-get install -y -qq "${packages[@]}"; } >"$log" 2>&1; then
    cat "$log" >&2
    echo "system-deps: could not install ${packages[*]} with apt-get (its output is above)" >&2
    exit 1
fi
echo "system-deps: installed ${packages[*]} (for ${missing[*]})"
