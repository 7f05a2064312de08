#!/bin/sh
# Checks the unit files the way systemd loads them, and prints their exposure
# scores. `systemd-analyze verify` exits 0 even on unknown keys and bad values,
# so any output at all is a failure here.
#
# The units name /usr/local/bin/sdsem{,-sim}, which need not exist on the machine
# running the check: they are verified inside a temporary root that holds the
# system's own units (sysinit.target…), stand-ins for the two binaries and
# /bin/kill (ExecReload).
set -eu
here=$(cd "$(dirname "$0")" && pwd)
root=$(mktemp -d)
trap 'rm -rf "$root"' EXIT

mkdir -p "$root/usr/local/bin" "$root/etc/systemd/system" "$root/usr/lib/systemd/system" "$root/bin"
for dir in /lib/systemd/system /usr/lib/systemd/system; do
    if [ -d "$dir" ]; then
        cp -a "$dir/." "$root/usr/lib/systemd/system/"
    fi
done
for bin in sdsem sdsem-sim; do
    install -m 755 /bin/true "$root/usr/local/bin/$bin"
done
# A stand-in for /bin/kill too: only its presence is checked.
install -m 755 /bin/true "$root/bin/kill"
cp "$here"/*.service "$root/etc/systemd/system/"

# Unit *files* (not names): by name, `verify --root` reports nothing at all.
if ! out=$(systemd-analyze verify --man=no --root="$root" "$root"/etc/systemd/system/*.service 2>&1) \
    || [ -n "$out" ]; then
    printf 'systemd-analyze verify complained:\n%s\n' "$out" >&2
    exit 1
fi
echo "systemd-analyze verify: no output for $(cd "$here" && echo *.service)"

for unit in "$here"/*.service; do
    score=$(systemd-analyze security --offline=yes --root="$root" "$root/etc/systemd/system/$(basename "$unit")" 2>&1 \
        | sed -n 's/.*Overall exposure level for .*: //p')
    echo "systemd-analyze security --offline=yes $(basename "$unit"): ${score:-unavailable}"
done
