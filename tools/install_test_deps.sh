#!/bin/sh
# Debian packages the vcan HIL tests need (docs/hil.md, "vcan0"):
#   user-mode-linux  a Linux kernel as an ordinary process, with the CAN modules
#                    (for machines whose own kernel has no vcan module)
#   kmod             insmod, to load those modules inside user-mode Linux
#   can-utils        candump, cansend, cangen (the interoperability tests)
# As root on a Debian-like machine the missing ones are installed with apt-get
# (non-interactive) and the script says so; otherwise it prints what is missing
# and exits 0: the tests that need a package skip with the reason.
# Called by `make test`; safe to run again (installs only what is missing).
set -u
missing=""
for pkg in user-mode-linux kmod can-utils; do
    if ! dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed"; then
        missing="$missing $pkg"
    fi
done
missing="${missing# }"
if [ -z "$missing" ]; then
    echo "install_test_deps: user-mode-linux, kmod, can-utils already installed"
    exit 0
fi
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 && command -v dpkg-query >/dev/null 2>&1; then
    echo "install_test_deps: installing $missing with apt-get (as root, non-interactive)"
    export DEBIAN_FRONTEND=noninteractive
    # shellcheck disable=SC2086 # one word per package
    if apt-get install -y -q --no-install-recommends $missing >/dev/null \
        || { apt-get update -q >/dev/null && apt-get install -y -q --no-install-recommends $missing >/dev/null; }; then
        echo "install_test_deps: installed $missing"
    else
        echo "install_test_deps: apt-get could not install $missing; the vcan tests will skip" >&2
    fi
else
    echo "install_test_deps: missing $missing (not root on a Debian-like machine: not installing);"
    echo "  the vcan tests will skip. To install: sudo apt-get install $missing"
fi
exit 0
