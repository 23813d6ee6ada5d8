#!/bin/sh
# Ensure the system libraries facegeo's Python dependencies need are present.
# open3d's Linux wheels link against libusb-1.0 (libusb-1.0.so.0), which slim images lack.
# Installs it with apt-get when running as root; otherwise says exactly what to install.
set -eu
[ "$(uname -s)" = "Linux" ] || exit 0

have_lib() {
    if command -v ldconfig >/dev/null 2>&1 && ldconfig -p 2>/dev/null | grep -q "$1"; then
        return 0
    fi
    for d in /lib /usr/lib /lib64 /usr/lib64 /usr/lib/x86_64-linux-gnu /lib/x86_64-linux-gnu \
             /usr/lib/aarch64-linux-gnu /lib/aarch64-linux-gnu; do
        [ -e "$d/$1" ] && return 0
    done
    return 1
}

missing=""
have_lib libusb-1.0.so.0 || missing="$missing libusb-1.0-0"
[ -z "$missing" ] && exit 0

if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null 2>&1; then
    echo "facegeo set-up: installing system packages:$missing" >&2
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq >/dev/null
    # shellcheck disable=SC2086
    apt-get install -y -qq --no-install-recommends $missing >/dev/null
    exit 0
fi

echo "facegeo set-up: missing system packages:$missing" >&2
echo "  open3d needs libusb-1.0 (libusb-1.0.so.0). Install it, e.g. on Debian/Ubuntu:" >&2
echo "    sudo apt-get install libusb-1.0-0" >&2
echo "  (Fedora: sudo dnf install libusbx; Arch: sudo pacman -S libusb), then run make again." >&2
exit 1
