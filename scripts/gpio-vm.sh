#!/usr/bin/env bash
# Runs a command on a real kernel GPIO chip: boots Debian's own 6.1 kernel under QEMU (software
# emulation, TCG) with an out-of-tree `gpio-sim` module, shares this machine's root file system
# with the guest over 9p, creates a fresh gpio-sim chip through configfs and runs COMMAND inside
# the guest, chrooted into this machine's root, in the current directory. Prints the command's
# output and exits with its status.
#
# Usage: scripts/gpio-vm.sh [--lines N] [--timeout S] [--cpus N] [--] COMMAND [ARGS...]
#        scripts/gpio-vm.sh --prepare     install and build only (no boot)
#   --lines N    lines of the gpio-sim chip (default 8)
#   --timeout S  kill the guest after S seconds of wall time (default 300)
#   --cpus N     the guest's virtual CPUs (default 2); each busy one takes a core of this machine
#
# In the guest COMMAND sees GPIO_SIM_CHIP (/dev/gpiochipN), GPIO_SIM_SYSFS (the chip's sysfs
# directory holding sim_gpioN/value and pull) and GPIO_SIM_LINES. It runs as root with the
# loopback interface up (DDS needs it).
#
# Everything built is cached in .gpio-vm/ (git-ignored) and rebuilt when an input changes: the
# kernel version, the module sources, busybox, or the parts of this script that build them.
# Debian packages are installed with apt-get when missing. Exit status: COMMAND's; 124 when the
# guest did not finish within the timeout (it was killed: a hang, never a skip); 125 when the
# guest could not be prepared or ended without reporting a status; 120 when this machine cannot
# run it at all (not Debian, or packages missing and not root to install them). The reason is
# printed.

set -euo pipefail

REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
CACHE="$REPO/.gpio-vm"
LINES=8
TIMEOUT=300
CPUS=2
PREPARE_ONLY=0
# Exit status when the guest itself could not run (distinct from the command's own statuses).
NO_GUEST=125
# Exit status when the guest ran out of time and was killed (timeout(1)'s own).
HUNG=124
# Exit status when this machine cannot run the guest at all (nothing failed).
NOT_HERE=120

die() {
    echo "gpio-vm: $*" >&2
    exit "$NO_GUEST"
}
say() { echo "gpio-vm: $*" >&2; }
not_here() {
    echo "gpio-vm: cannot run on this machine: $*" >&2
    exit "$NOT_HERE"
}

while (($#)); do
    case "$1" in
        --lines) LINES=${2:?--lines needs a number}; shift ;;
        --timeout) TIMEOUT=${2:?--timeout needs seconds}; shift ;;
        --cpus) CPUS=${2:?--cpus needs a number}; shift ;;
        --prepare) PREPARE_ONLY=1 ;;
        -h | --help) sed -n '2,24p' "${BASH_SOURCE[0]}" | sed 's/^# \{0,1\}//'; exit 0 ;;
        --) shift; break ;;
        -*) die "unknown option '$1' (try --help)" ;;
        *) break ;;
    esac
    shift
done
[[ "$LINES" =~ ^[1-9][0-9]*$ ]] || die "--lines: '$LINES' is not a positive number"
[[ "$TIMEOUT" =~ ^[1-9][0-9]*$ ]] || die "--timeout: '$TIMEOUT' is not a positive number"
[[ "$CPUS" =~ ^[1-8]$ ]] || die "--cpus: '$CPUS' is not a number from 1 to 8"
if ((!PREPARE_ONLY && $# == 0)); then
    die "no command given (try --help)"
fi

# ---- 1. Debian packages ------------------------------------------------------------------------

apt_updated=0
apt_install() {
    ((EUID == 0)) || not_here "needs Debian packages ($*) and is not root: install them first"
    if ((!apt_updated)); then
        say "apt-get update"
        apt-get update -qq >&2 || die "apt-get update failed"
        apt_updated=1
    fi
    say "installing $*"
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "$@" >&2 \
        || die "apt-get install $* failed"
}

command -v apt-get >/dev/null || not_here "needs apt-get (Debian 12)"
missing=()
command -v qemu-system-x86_64 >/dev/null || missing+=(qemu-system-x86)
[[ -x /bin/busybox ]] || missing+=(busybox-static)
command -v cpio >/dev/null || missing+=(cpio)
command -v xz >/dev/null || missing+=(xz-utils)
((${#missing[@]} == 0)) || apt_install "${missing[@]}"
# (Not `busybox --list | grep -q`: with pipefail, grep's early exit fails the pipeline.)
[[ $'\n'"$(/bin/busybox --list)"$'\n' == *$'\nip\n'* ]] \
    || die "/bin/busybox has no 'ip' applet: needs busybox-static"

# The kernel: the ABI Debian's linux-image-amd64 points at (bookworm: 6.1.0-NN-amd64).
# (On a machine without any headers `ls` fails: under pipefail that must not end the script.)
KVER="$({ ls -d /usr/src/linux-headers-6.1.0-*-amd64 2>/dev/null || true; } | sort -V | tail -n1 | sed 's|.*/linux-headers-||')"
if [[ -z "$KVER" ]]; then
    abi="$(apt-cache depends linux-image-amd64 2>/dev/null | sed -n 's/.*Depends: linux-image-\(6\.1\.0-[0-9]*-amd64\)$/\1/p' | head -n1)"
    if [[ -z "$abi" ]]; then
        apt-get update -qq >&2 || die "apt-get update failed"
        apt_updated=1
        abi="$(apt-cache depends linux-image-amd64 | sed -n 's/.*Depends: linux-image-\(6\.1\.0-[0-9]*-amd64\)$/\1/p' | head -n1)"
    fi
    [[ -n "$abi" ]] || die "cannot tell which linux-image-6.1.0-NN-amd64 is current (apt-cache depends linux-image-amd64)"
    KVER="$abi"
fi
HEADERS="/usr/src/linux-headers-$KVER"
[[ -d "$HEADERS" ]] || apt_install "linux-headers-$KVER"
SRC_TAR=/usr/src/linux-source-6.1.tar.xz
[[ -f "$SRC_TAR" ]] || apt_install linux-source-6.1
[[ -d "$HEADERS" ]] || die "$HEADERS missing after installing linux-headers-$KVER"
[[ -f "$SRC_TAR" ]] || die "$SRC_TAR missing after installing linux-source-6.1"

# ---- 2. The kernel image and its modules (unpacked, not installed) -----------------------------

mkdir -p "$CACHE"
exec 9>"$CACHE/.lock"
flock 9 # one builder at a time; runs below only read the cache

IMAGE="$CACHE/image-$KVER"
if [[ ! -f "$IMAGE/boot/vmlinuz-$KVER" ]]; then
    say "fetching linux-image-$KVER"
    rm -rf "$CACHE/debs" "$IMAGE"
    mkdir -p "$CACHE/debs"
    if ! (cd "$CACHE/debs" && apt-get download -q "linux-image-$KVER" >&2); then
        say "apt-get download failed; retrying after apt-get update"
        apt-get update -qq >&2 || die "apt-get update failed"
        (cd "$CACHE/debs" && apt-get download -q "linux-image-$KVER" >&2) \
            || die "apt-get download linux-image-$KVER failed"
    fi
    deb="$(ls "$CACHE"/debs/linux-image-"$KVER"_*.deb | head -n1)"
    dpkg-deb -x "$deb" "$IMAGE.tmp" || die "dpkg-deb -x $deb failed"
    mv "$IMAGE.tmp" "$IMAGE"
    rm -rf "$CACHE/debs"
fi
[[ -f "$IMAGE/boot/vmlinuz-$KVER" ]] || die "no vmlinuz in linux-image-$KVER"

# ---- 3. gpio-sim.ko and the initramfs, rebuilt when an input changes ---------------------------

# The modules the guest loads, in dependency order (modprobe --show-depends on this kernel);
# those built into the kernel are skipped.
GUEST_MODULES=(virtio_ring virtio virtio_pci_modern_dev virtio_pci_legacy_dev virtio_pci
    9pnet 9pnet_virtio netfs fscache 9p configfs)

# The guest's /init. $LINES and the run directory come on the kernel command line.
read -r -d '' GUEST_INIT <<'EOF' || true
#!/bin/busybox sh
/bin/busybox --install -s /bin
export PATH=/bin
mkdir -p /proc /sys /dev /mnt/host
mount -t proc proc /proc
mount -t sysfs sysfs /sys
mount -t devtmpfs devtmpfs /dev
fail() { echo "gpio-vm guest: $*" >/dev/console; poweroff -f; }
for m in $(cat /modules.order); do
    insmod "/modules/$m.ko" || fail "insmod $m failed"
done
mount -t configfs none /sys/kernel/config || fail "cannot mount configfs"
ip link set lo up || fail "ip link set lo up failed"
mount -t 9p -o trans=virtio,version=9p2000.L,msize=512000,access=any host /mnt/host \
    || fail "cannot mount the host root over 9p"
lines=8 run=
for a in $(cat /proc/cmdline); do
    case "$a" in
        gpiovm.lines=*) lines=${a#gpiovm.lines=} ;;
        gpiovm.run=*) run=${a#gpiovm.run=} ;;
    esac
done
[ -n "$run" ] || fail "no gpiovm.run= on the kernel command line"
cfg=/sys/kernel/config/gpio-sim/gpio-vm
mkdir "$cfg" "$cfg/bank0" || fail "cannot create a gpio-sim chip in configfs"
echo "$lines" >"$cfg/bank0/num_lines"
echo gpio-sim-vm >"$cfg/bank0/label"
echo 1 >"$cfg/live" || fail "cannot bring the gpio-sim chip live"
chip=$(cat "$cfg/bank0/chip_name") dev=$(cat "$cfg/dev_name")
for d in proc sys dev; do mount -o bind "/$d" "/mnt/host/$d"; done
mkdir -p /mnt/host/dev/shm && mount -t tmpfs tmpfs /mnt/host/dev/shm
cd /mnt/host
env -i HOME=/root PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
    LANG=C.UTF-8 TERM=dumb GPIO_SIM_CHIP="/dev/$chip" \
    GPIO_SIM_SYSFS="/sys/devices/platform/$dev/$chip" GPIO_SIM_LINES="$lines" \
    chroot /mnt/host /bin/sh "$run/run.sh" >/dev/console 2>&1 </dev/null
echo $? >"/mnt/host$run/status"
sync
poweroff -f
EOF

# Kbuild and the one change to irq_sim.c: irq_to_desc() is not exported by this kernel, and
# generic_handle_irq() does the same job for a virq.
KBUILD=$'obj-m := gpio-sim.o\ngpio-sim-y := gpio-sim-main.o irq_sim.o\n'
patch_irq_sim() {
    sed -i 's/handle_simple_irq(irq_to_desc(\([^)]*\)))/generic_handle_irq(\1)/' irq_sim.c
    grep -q 'irq_to_desc' irq_sim.c && return 1
    return 0
}

inputs_hash() {
    {
        echo "$KVER"
        sha256sum "$SRC_TAR" "/bin/busybox" "$IMAGE/boot/vmlinuz-$KVER" | cut -d' ' -f1
        printf '%s\n' "${GUEST_MODULES[@]}" "$GUEST_INIT" "$KBUILD"
        declare -f patch_irq_sim
    } | sha256sum | cut -d' ' -f1
}
# Hashing the 140 MB source tarball costs a second on every run, so the hash is reused while
# the files keep their size and mtime (line 1 of .gpio-vm/inputs) and this script's own build
# inputs are unchanged (line 3); otherwise it is computed again in full.
src_stamp="$(stat -c '%s %Y' "$SRC_TAR" /bin/busybox "$IMAGE/boot/vmlinuz-$KVER" | tr '\n' ' ')"
HASH=""
if [[ -f "$CACHE/inputs" ]] && [[ "$(sed -n 1p "$CACHE/inputs")" == "$src_stamp" ]]; then
    HASH="$(sed -n 2p "$CACHE/inputs")"
fi
self_hash="$({ printf '%s\n' "${GUEST_MODULES[@]}" "$GUEST_INIT" "$KBUILD"; declare -f patch_irq_sim; } | sha256sum | cut -d' ' -f1)"
if [[ -z "$HASH" || "$(sed -n 3p "$CACHE/inputs" 2>/dev/null)" != "$self_hash" ]]; then
    HASH="$(inputs_hash)"
    printf '%s\n%s\n%s\n' "$src_stamp" "$HASH" "$self_hash" >"$CACHE/inputs"
fi
BUILT="$CACHE/built-$HASH"

if [[ ! -f "$BUILT/initrd.gz" ]]; then
    say "building gpio-sim.ko and the initramfs for $KVER (cache $BUILT)"
    rm -rf "$CACHE"/built-* "$CACHE/build"
    work="$CACHE/build"
    mkdir -p "$work/mod" "$work/src" "$work/root"
    tar -xJf "$SRC_TAR" -C "$work/src" --wildcards \
        'linux-source-6.1/drivers/gpio/gpio-sim.c' 'linux-source-6.1/drivers/gpio/gpiolib*.h' \
        'linux-source-6.1/kernel/irq/irq_sim.c' \
        || die "cannot extract gpio-sim.c, gpiolib*.h and irq_sim.c from $SRC_TAR"
    s="$work/src/linux-source-6.1"
    cp "$s/drivers/gpio/gpio-sim.c" "$work/mod/gpio-sim-main.c"
    cp "$s"/drivers/gpio/gpiolib*.h "$s/kernel/irq/irq_sim.c" "$work/mod/"
    printf '%s' "$KBUILD" >"$work/mod/Kbuild"
    (cd "$work/mod" && patch_irq_sim) || die "irq_sim.c: could not replace irq_to_desc()"
    make -s -C "$HEADERS" M="$work/mod" modules >"$work/make.log" 2>&1 \
        || { tail -n 30 "$work/make.log" >&2; die "building gpio-sim.ko failed (log: $work/make.log)"; }

    r="$work/root"
    mkdir -p "$r/bin" "$r/dev" "$r/modules"
    cp /bin/busybox "$r/bin/busybox"
    mknod -m 600 "$r/dev/console" c 5 1
    mknod -m 666 "$r/dev/null" c 1 3
    : >"$r/modules.order"
    builtin="$IMAGE/lib/modules/$KVER/modules.builtin"
    for m in "${GUEST_MODULES[@]}"; do
        f="$(find "$IMAGE/lib/modules/$KVER/kernel" -name "$m.ko" -o -name "$m.ko.xz" | head -n1)"
        if [[ -z "$f" ]]; then
            grep -q "/$m.ko$" "$builtin" 2>/dev/null || die "module $m not found in linux-image-$KVER"
            continue
        fi
        case "$f" in
            *.xz) xz -dc "$f" >"$r/modules/$m.ko" ;;
            *) cp "$f" "$r/modules/$m.ko" ;;
        esac
        echo "$m" >>"$r/modules.order"
    done
    cp "$work/mod/gpio-sim.ko" "$r/modules/gpio-sim.ko"
    echo gpio-sim >>"$r/modules.order"
    printf '%s\n' "$GUEST_INIT" >"$r/init"
    chmod 755 "$r/init"
    mkdir -p "$BUILT.tmp"
    (cd "$r" && find . | cpio -o -H newc --quiet | gzip -1) >"$BUILT.tmp/initrd.gz" \
        || die "cannot pack the initramfs"
    cp "$IMAGE/boot/vmlinuz-$KVER" "$BUILT.tmp/vmlinuz"
    mv "$BUILT.tmp" "$BUILT"
    rm -rf "$work"
fi
exec 9>&- # the cache is complete; runs proceed in parallel

if ((PREPARE_ONLY)); then
    say "ready: $BUILT"
    exit 0
fi

# ---- 4. Boot, run, report ----------------------------------------------------------------------

mkdir -p "$CACHE/run"
RUN="$(mktemp -d "$CACHE/run/XXXXXX")"
trap 'rm -rf "$RUN"' EXIT
{
    echo "cd $(printf '%q' "$PWD") || exit 126"
    printf 'exec'
    printf ' %q' "$@"
    echo
} >"$RUN/run.sh"

start=$SECONDS
set +e
timeout --foreground -k 5 "$TIMEOUT" qemu-system-x86_64 \
    -accel tcg,thread=multi -cpu max -smp "$CPUS" -m 1024 -nographic -no-reboot -nic none \
    -kernel "$BUILT/vmlinuz" -initrd "$BUILT/initrd.gz" \
    -append "console=ttyS0 quiet loglevel=1 panic=-1 gpiovm.lines=$LINES gpiovm.run=$RUN" \
    -virtfs local,path=/,mount_tag=host,security_model=none,multidevs=remap \
    </dev/null | tr -d '\r' | sed -u -e 's/\x1b\[[0-9;?]*[a-zA-Z]//g; s/\x1bc//g' \
        -e 's/^SeaBIOS (version [^)]*)//; s/^Booting from ROM\.*//; /reboot: Power down$/d; /^$/d'
qemu_rc=${PIPESTATUS[0]}
set -e
if [[ -f "$RUN/status" ]]; then
    status="$(cat "$RUN/status")"
    say "guest command exited $status ($((SECONDS - start)) s)"
    exit "$status"
fi
if ((qemu_rc == 124 || qemu_rc == 137)); then
    say "the guest did not finish within ${TIMEOUT} s (killed)"
    exit "$HUNG"
fi
die "the guest ended without reporting the command's status (qemu exit $qemu_rc)"
