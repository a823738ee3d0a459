#!/bin/sh
# What the vcan HIL tests need (docs/hil.md, "vcan0"), and systemd-analyze for the deploy test, set up idempotently:
#
# 1. Debian packages:
#      user-mode-linux  a Linux kernel as an ordinary process, with the CAN modules
#                       (for machines whose own kernel has no vcan module)
#      kmod             insmod, to load those modules inside user-mode Linux
#      can-utils        candump, cansend, cangen (the interoperability tests)
#      patchelf         to point a newer UML at its own C library (step 3)
#      systemd          for systemd-analyze: tests/firmware_py/test_deploy_doc.py runs `systemd-analyze
#                       verify` on the shipped units (works without systemd as PID 1)
#    As root on a Debian-like machine the missing ones are installed with
#    apt-get (non-interactive); otherwise the script says what is missing.
# 2. Which way to a kernel vcan0 works here: `python -m ground_station.lab.rigs.vcan`
#    boots each provider once (host kernel, the installed UML, the cached UML).
# 3. If none works (bookworm's UML 6.1 and trixie's 6.12 panic at boot on CPUs
#    with AVX-512/AMX: "ptrace set fp regs failed"), Debian testing's
#    user-mode-linux (7.x boots there) is downloaded with apt-get into a private
#    apt state and unpacked, with that suite's libc6 (it needs glibc >= 2.38),
#    into .cache/uml/ of the checkout (nothing is installed into the system);
#    patchelf points the kernel binary at that C library. Then step 2 again.
#
# It never fails `make test`: when no provider works, the vcan tests skip with
# the reason printed. Environment: PYTHON (default .venv/bin/python, else
# python3), QNAV_UML_CACHE (default .cache/uml), QNAV_UML_SUITE (default testing),
# QNAV_UML_FETCH=1 (unpack the newer UML even where another provider works).
set -u
cd "$(dirname "$0")/.." || exit 0
say() { echo "install_test_deps: $*"; }

missing=""
for pkg in user-mode-linux kmod can-utils patchelf systemd; do
    if ! dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed"; then
        missing="$missing $pkg"
    fi
done
missing="${missing# }"
root_apt=no
if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1 && command -v dpkg-query >/dev/null 2>&1; then
    root_apt=yes
fi
if [ -z "$missing" ]; then
    say "user-mode-linux, kmod, can-utils, patchelf, systemd already installed"
elif [ "$root_apt" = yes ]; then
    say "installing $missing with apt-get (as root, non-interactive)"
    export DEBIAN_FRONTEND=noninteractive
    # shellcheck disable=SC2086 # one word per package
    if apt-get install -y -q --no-install-recommends $missing >/dev/null \
        || { apt-get update -q >/dev/null && apt-get install -y -q --no-install-recommends $missing >/dev/null; }; then
        say "installed $missing"
    else
        say "apt-get could not install $missing; tests that need them will skip" >&2
    fi
else
    say "missing $missing (not root on a Debian-like machine: not installing);"
    echo "  the vcan tests will skip. To install: sudo apt-get install $missing"
fi

PY="${PYTHON:-.venv/bin/python}"
[ -x "$PY" ] || PY=python3
providers() { "$PY" -m ground_station.lab.rigs.vcan | sed 's/^/  /'; }

verdict=$(providers)
if [ "${QNAV_UML_FETCH:-0}" != 1 ] && echo "$verdict" | grep -q "^  chosen:"; then
    say "kernel vcan0:"; echo "$verdict"
    exit 0
fi

cache="${QNAV_UML_CACHE:-$PWD/.cache/uml}"
suite="${QNAV_UML_SUITE:-testing}"
if [ "$root_apt" = no ] || ! command -v patchelf >/dev/null 2>&1; then
    say "no provider works and a newer UML cannot be fetched here (needs apt-get and patchelf):"
    echo "$verdict"
    exit 0
fi
if [ "${QNAV_UML_FETCH:-0}" = 1 ]; then why="QNAV_UML_FETCH=1"; else why="no provider works yet"; fi
say "$why; unpacking Debian $suite's user-mode-linux into $cache"
apt_dir="$cache.apt"
rm -rf "$cache.new" && mkdir -p "$apt_dir/lists/partial" "$apt_dir/archives/partial" "$apt_dir/etc" "$cache.new" || exit 0
: > "$apt_dir/status"
echo "deb [signed-by=/usr/share/keyrings/debian-archive-keyring.gpg] http://deb.debian.org/debian $suite main" \
    > "$apt_dir/etc/sources.list"
# a private apt state: the system's package lists and sources are not touched
apt_opts="-q -o Dir::State::Lists=$apt_dir/lists -o Dir::State::status=$apt_dir/status
 -o Dir::Cache::Archives=$apt_dir/archives -o Dir::Cache=$apt_dir -o Dir::Etc::SourceList=$apt_dir/etc/sources.list
 -o Dir::Etc::SourceParts=/nonexistent -o APT::Sandbox::User=root"
# shellcheck disable=SC2086 # one word per option
if ! apt-get $apt_opts update >/dev/null \
    || ! (cd "$apt_dir/archives" && apt-get $apt_opts download user-mode-linux libc6 >/dev/null); then
    say "could not download user-mode-linux and libc6 from Debian $suite; the vcan tests will skip" >&2
    echo "$verdict"
    exit 0
fi
for deb in "$apt_dir"/archives/user-mode-linux_*.deb "$apt_dir"/archives/libc6_*.deb; do
    dpkg -x "$deb" "$cache.new" || { say "dpkg -x $deb failed" >&2; exit 0; }
done
libdir="$cache/usr/lib/x86_64-linux-gnu"
[ -d "$cache.new/usr/lib/x86_64-linux-gnu" ] || libdir="$cache/lib/x86_64-linux-gnu"
# the final paths, so the cache is moved into place before it is run; UML's memory
# layout check rejects a start through `ld.so --library-path`, hence patchelf
patchelf --set-interpreter "$libdir/ld-linux-x86-64.so.2" --set-rpath "$libdir" \
    "$cache.new/usr/bin/linux.uml" || { say "patchelf failed" >&2; exit 0; }
rm -rf "$cache" && mv "$cache.new" "$cache" || exit 0
say "unpacked $(ls "$apt_dir"/archives/*.deb | xargs -n1 basename | tr '\n' ' ')"
say "kernel vcan0:"; providers
exit 0
