#!/usr/bin/env bash
# Build bench/gwyddion/tip_harness against Debian's Gwyddion (libgwyprocess).
# Installs libgwyddion20-dev, libgtk2.0-dev, pkg-config and gcc with apt-get when
# `pkg-config --exists gwyddion` fails; otherwise installs nothing. gwyddion.pc also Requires
# fftw3 and gtkglext-1.0, which Debian's libgwyddion20-dev does not pull in, so libfftw3-dev and
# libgtkglext1-dev are installed too (without them pkg-config rejects the module).
# Debian 12 ships one pkg-config module for all Gwyddion libraries, "gwyddion" (gwyddion.pc,
# Libs: -lgwyapp2 ... -lgwyprocess2 -lgwyddion2); there is no separate libgwyprocess module.
# Rebuilds only when the source is newer than the binary (or with --force).
set -euo pipefail
here="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
src="$here/tip_harness.c"
out="$here/tip_harness"

if ! { command -v pkg-config >/dev/null && command -v gcc >/dev/null && pkg-config --exists gwyddion; }; then
    if [ "$(id -u)" -ne 0 ]; then
        echo "build.sh: Gwyddion development files missing; run as root or install:" \
             "libgwyddion20-dev libgtk2.0-dev libfftw3-dev libgtkglext1-dev pkg-config gcc" >&2
        exit 1
    fi
    echo "build.sh: installing Gwyddion development packages" >&2
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq --no-install-recommends libgwyddion20-dev libgtk2.0-dev \
        libfftw3-dev libgtkglext1-dev pkg-config gcc libc6-dev >&2
    if ! pkg-config --exists gwyddion; then
        echo "build.sh: pkg-config still rejects gwyddion:" >&2
        pkg-config --print-errors --exists gwyddion >&2
        exit 1
    fi
fi

if [ "${1:-}" = "--force" ] || [ ! -x "$out" ] || [ "$src" -nt "$out" ]; then
    # --as-needed keeps the binary linked to libgwyprocess2/libgwyddion2 (+glib/gomp) only, although
    # gwyddion.pc lists the GUI libraries too. -fopenmp for omp_set_num_threads (libgomp is what
    # libgwyprocess2 already uses).
    # shellcheck disable=SC2046
    gcc -O2 -std=gnu99 -Wall -Werror=implicit-function-declaration -fopenmp -o "$out" "$src" \
        $(pkg-config --cflags gwyddion) -Wl,--as-needed $(pkg-config --libs gwyddion) -lm
    echo "build.sh: built $out" >&2
fi
