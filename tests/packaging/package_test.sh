#!/bin/bash
# The .deb (issue 6): build it with cpack, extract it into a scratch root with dpkg-deb -x, check
# the expected files, then start the installed cortexfused from that root with the shipped
# default configuration (its /usr/share paths moved into the root, a temporary state folder, a
# free port): GET /api/status must answer, the MRI must load from the installed data, and the
# case store must be created on first start. Skips (77) without dpkg-deb, cpack, jq or curl.
# Then the installed cortexfuse and cortexfused find the bundled data from the installed layout
# (<prefix>/share/cortexfuse/data beside <prefix>/bin), not the build tree: `cortexfuse phantom`
# runs with its defaults from the scratch root with the source tree's data/ hidden (an empty
# tmpfs over it in a private mount namespace, where unshare is allowed), and CF_DATA_DIR still
# points elsewhere.
# Usage: package_test.sh BUILD_DIR CPACK [SOURCE_DIR]
set -euo pipefail
build=$1
cpack=${2:-cpack}
src=${3:-}
for t in dpkg-deb jq curl "$cpack"; do
    command -v "$t" >/dev/null || { echo "$t not installed: skipped"; exit 77; }
done
tmp=$(mktemp -d /tmp/cf-package-test-XXXXXX)
pid=
cleanup() {
    if [ -n "$pid" ] && kill -0 "$pid" 2>/dev/null; then kill -KILL "$pid"; fi
    rm -rf "$tmp"
}
trap cleanup EXIT
fail() { echo "FAIL: $*"; [ -f "$tmp/daemon.log" ] && { echo "--- daemon log"; tail -40 "$tmp/daemon.log"; }; exit 1; }

# 1. The package. (-B: its scratch and the .deb stay out of the build folder.)
[ -f "$build/CPackConfig.cmake" ] || fail "$build has no CPackConfig.cmake (configure the project first)"
(cd "$build" && "$cpack" -G DEB -B "$tmp/pkg" >"$tmp/cpack.log" 2>&1) || { cat "$tmp/cpack.log"; fail "cpack -G DEB"; }
deb=$(ls "$tmp"/pkg/cortexfuse_*.deb 2>/dev/null | head -1)
[ -n "$deb" ] || { cat "$tmp/cpack.log"; fail "cpack made no cortexfuse_*.deb"; }
echo "package: $(basename "$deb") ($(stat -c %s "$deb") bytes)"

# 2. Control data.
dpkg-deb -f "$deb" Package | grep -qx cortexfuse || fail "Package is not cortexfuse"
dpkg-deb -f "$deb" Depends | grep -q libcivetweb || fail "Depends lacks the shared libraries (dpkg-shlibdeps): $(dpkg-deb -f "$deb" Depends)"
mkdir "$tmp/control"
dpkg-deb -e "$deb" "$tmp/control"
for f in /etc/cortexfuse/cortexfused.json /etc/default/cortexfused; do
    grep -qx "$f" "$tmp/control/conffiles" || fail "$f is not a conffile"
done
for s in postinst prerm postrm; do
    [ -x "$tmp/control/$s" ] || fail "maintainer script $s missing or not executable"
    sh -n "$tmp/control/$s" || fail "maintainer script $s: syntax error"
done

# The CPU baseline (docs/packaging.md): named in the description; a portable build (CF_NATIVE=OFF,
# scripts/build-package.sh) must hold no instruction beyond it in its binaries: no EVEX (AVX-512)
# for x86-64-v3, no VEX (AVX) either for x86-64-v2 and plain x86-64. In 64-bit code an instruction
# whose first byte (after an optional 67 prefix) is 62 is EVEX, c4/c5 VEX.
dpkg-deb -f "$deb" Description | grep -q "CPU baseline: " || fail "the description does not name the CPU baseline: $(dpkg-deb -f "$deb" Description)"
native=$(sed -n 's/^CF_NATIVE:BOOL=//p' "$build/CMakeCache.txt")
march=$(sed -n 's/^CF_MARCH:STRING=//p' "$build/CMakeCache.txt")
isa_check=
case "$native:$march" in
    ON:*|TRUE:*|1:*) echo "CPU baseline: native (this machine's CPU only; scripts/build-package.sh makes the portable package)" ;;
    *:x86-64-v3) isa_check='^62$' ;;
    *:x86-64-v2|*:x86-64|*:) isa_check='^(62|c4|c5)$' ;;
    *) echo "CPU baseline: $march (no instruction scan for it)" ;;
esac
if [ -n "$isa_check" ] && command -v objdump >/dev/null; then
    for f in cortexfused cortexfuse; do
        mkdir -p "$tmp/isa"
        dpkg-deb --fsys-tarfile "$deb" | tar -x -C "$tmp/isa" "./usr/bin/$f"
        bad=$(objdump -d --no-addresses "$tmp/isa/usr/bin/$f" | awk -F'\t' -v re="$isa_check" '
            NF >= 3 { split($2, b, " "); first = (b[1] == "67") ? b[2] : b[1]; if (first ~ re) { n++; if (n <= 3) ex = ex " | " $3 } }
            END { if (n) print n " instructions beyond the baseline, e.g." ex }')
        [ -z "$bad" ] || fail "usr/bin/$f is built for CPU baseline ${march:-x86-64} but holds $bad"
    done
    echo "CPU baseline: ${march:-x86-64}, no instruction beyond it in cortexfused and cortexfuse (objdump)"
fi

# 3. Files.
root=$tmp/root
dpkg-deb -x "$deb" "$root"
for f in usr/bin/cortexfused usr/bin/cortexfuse \
         usr/share/cortexfuse/data/t1_head_mne_ecog.nii.gz \
         usr/share/cortexfuse/data/brainmask_mne_ecog_binary.nii.gz \
         usr/share/cortexfuse/data/SOURCES.md \
         lib/systemd/system/cortexfused.service lib/udev/rules.d/70-cortexfuse.rules \
         etc/cortexfuse/cortexfused.json etc/default/cortexfused \
         usr/share/doc/cortexfuse/daemon.md usr/share/doc/cortexfuse/copyright \
         usr/share/doc/cortexfuse/api/status.md; do
    [ -s "$root/$f" ] || fail "$f missing or empty in the package"
done
for f in usr/bin/cortexfused usr/bin/cortexfuse; do
    [ -x "$root/$f" ] || fail "$f not executable"
    if ldd "$root/$f" | grep -q "not found"; then fail "$f: $(ldd "$root/$f" | grep 'not found' | head -3)"; fi
done
grep -q '^ExecStart=/usr/bin/cortexfused' "$root/lib/systemd/system/cortexfused.service" || fail "unit's ExecStart is not /usr/bin/cortexfused"
grep -q 'CORTEXFUSED_ARGS=.*--config /etc/cortexfuse/cortexfused.json' "$root/etc/default/cortexfused" || fail "/etc/default/cortexfused does not name the configuration"
[ "$(jq -r .data.t1 "$root/etc/cortexfuse/cortexfused.json")" = /usr/share/cortexfuse/data/t1_head_mne_ecog.nii.gz ] ||
    fail "the default configuration's data.t1 is not the installed MRI"
if [ -f "$root/usr/share/cortexfuse/ui/index.html" ]; then echo "UI: included"; else echo "UI: not in this package (ui/dist was not built)"; fi

# 4. The installed daemon, with the shipped configuration moved into the root.
sed "s#/usr/share/cortexfuse#$root/usr/share/cortexfuse#g" "$root/etc/cortexfuse/cortexfused.json" >"$tmp/config.json"
env -u CF_DATA_DIR "$root/usr/bin/cortexfused" --config "$tmp/config.json" --check-config >"$tmp/check.log" 2>&1 ||
    { cat "$tmp/check.log"; fail "the shipped configuration does not validate"; }
env -u CF_DATA_DIR -u STATE_DIRECTORY "$root/usr/bin/cortexfused" --config "$tmp/config.json" \
    --listen 127.0.0.1:0 --state-dir "$tmp/state" >"$tmp/daemon.log" 2>&1 &
pid=$!
port=
for _ in $(seq 300); do
    port=$(sed -n 's#.*listening on http://127\.0\.0\.1:\([0-9]*\)/.*#\1#p' "$tmp/daemon.log" | head -1)
    [ -n "$port" ] && break
    kill -0 "$pid" 2>/dev/null || fail "the installed cortexfused exited before listening"
    sleep 0.1
done
[ -n "$port" ] || fail "the installed cortexfused did not listen within 30 s"
status=$(curl -sf "http://127.0.0.1:$port/api/status") || fail "GET /api/status did not answer 200"
echo "$status" | jq -e '.name == "cortexfused" and (.version | type == "string")' >/dev/null || fail "status: $status"
[ -f "$tmp/state/store/cortexfuse.sqlite" ] || fail "no case store created on first start in state/store"
# The renderer loads the MRI named by the configuration (the installed copy).
state=
for _ in $(seq 600); do
    state=$(curl -sf "http://127.0.0.1:$port/api/status" | jq -r .modules.renderer.state)
    [ "$state" = loading ] || break
    sleep 0.1
done
[ "$state" = ready ] || fail "renderer state '$state' (the installed MRI did not load)"
curl -sf "http://127.0.0.1:$port/api/config" | jq -e --arg t "$root/usr/share/cortexfuse/data/t1_head_mne_ecog.nii.gz" '.data.t1 == $t' >/dev/null ||
    fail "the daemon does not use the installed data.t1"
kill -TERM "$pid"
rc=0
wait "$pid" || rc=$?
pid=
[ "$rc" = 0 ] || fail "cortexfused exited $rc on SIGTERM"

# 5. The installed binaries' data paths: the installed layout, not the build tree; CF_DATA_DIR wins.
share=$root/usr/share/cortexfuse
cli=$root/usr/bin/cortexfuse
t1=$(env -u CF_DATA_DIR -u CF_UI_DIR "$root/usr/bin/cortexfused" --print-default-config | jq -r .data.t1)
[ "$t1" = "$share/data/t1_head_mne_ecog.nii.gz" ] || fail "the installed cortexfused's default data.t1 is $t1, not the installed MRI"
if [ -f "$share/ui/index.html" ]; then
    ui=$(env -u CF_DATA_DIR -u CF_UI_DIR "$root/usr/bin/cortexfused" --print-default-config | jq -r .http.ui_dir)
    [ "$ui" = "$share/ui" ] || fail "the installed cortexfused's default http.ui_dir is $ui, not the installed UI"
fi
t1=$(CF_DATA_DIR=/srv/elsewhere "$root/usr/bin/cortexfused" --print-default-config | jq -r .data.t1)
[ "$t1" = /srv/elsewhere/t1_head_mne_ecog.nii.gz ] || fail "CF_DATA_DIR does not move the daemon's data.t1 ($t1)"
env -u CF_DATA_DIR "$cli" phantom --help | grep -qF "$share/data/t1_head_mne_ecog.nii.gz" ||
    fail "the installed cortexfuse's default --volume is not the installed MRI: $(env -u CF_DATA_DIR "$cli" phantom --help | grep -- --volume)"
# `cortexfuse phantom` with its default volume and mask, the build tree's data/ out of reach.
phantom_cmd=(env -u CF_DATA_DIR "$cli" phantom "$tmp/phantom" --n 1 --size 160x120 --fixed-size)
if [ -n "$src" ] && [ -d "$src/data" ] && [ "$(id -u)" = 0 ] && unshare -m true 2>/dev/null; then
    unshare -m sh -c 'mount -t tmpfs cf-hidden "$1" && [ ! -e "$1/t1_head_mne_ecog.nii.gz" ] && shift && exec "$@"' sh "$src/data" \
        "${phantom_cmd[@]}" >"$tmp/phantom.log" 2>&1 || { cat "$tmp/phantom.log"; fail "installed cortexfuse phantom (build tree's data/ hidden)"; }
    echo "cortexfuse phantom: ran with $src/data hidden"
else
    "${phantom_cmd[@]}" >"$tmp/phantom.log" 2>&1 || { cat "$tmp/phantom.log"; fail "installed cortexfuse phantom"; }
    echo "cortexfuse phantom: ran (no private mount namespace here: the build tree's data/ stayed visible)"
fi
[ -s "$tmp/phantom/case_0000/case.json" ] || fail "installed cortexfuse phantom wrote no case_0000/case.json"
# CF_DATA_DIR points the CLI elsewhere: a folder without the MRI is refused naming it.
if CF_DATA_DIR="$tmp/no-data" "$cli" phantom "$tmp/phantom2" --n 1 >"$tmp/phantom2.log" 2>&1; then
    fail "cortexfuse phantom succeeded with CF_DATA_DIR=$tmp/no-data"
fi
grep -qF "$tmp/no-data" "$tmp/phantom2.log" || { cat "$tmp/phantom2.log"; fail "the error does not name CF_DATA_DIR's folder"; }
echo "ok"
