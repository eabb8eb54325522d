#!/usr/bin/env bash
# `make docker-test`: build both images with buildah (no Docker engine, no container
# registry: the base is a local stand-in for python:3.12-slim-bookworm, docker/base.sh) and
# run them:
#   offline image   mesh the coarse cornea, solve it and train a tiny campaign under
#                   mpirun -n 2, compiling no form (its JIT cache was filled at build time);
#   runtime image   play and bench that model (a host file, mounted read only) without the
#                   finite-element stack, and time a container's start to its first step.
# Root, with buildah and debootstrap (apt-get install buildah debootstrap). The base image is
# kept (built again with DOCKER_TEST_REBUILD_BASE=1); the test images, containers and files
# go at the end unless DOCKER_TEST_KEEP=1 (which also keeps buildah's layer cache).
set -euo pipefail
cd "$(dirname "$0")/.."

BASE=${DOCKER_TEST_BASE:-localhost/hapticrom-base:3.12-bookworm}
OFFLINE=localhost/hapticrom-offline:test
RUNTIME=localhost/hapticrom-runtime:test
KEEP=${DOCKER_TEST_KEEP:-0}
ISO=(--isolation chroot)

for tool in buildah debootstrap; do
    command -v "$tool" >/dev/null || { echo "docker-test: needs $tool (apt-get install buildah debootstrap)" >&2; exit 1; }
done
[ "$(id -u)" = 0 ] || { echo "docker-test: run as root (buildah --isolation chroot)" >&2; exit 1; }

START=$SECONDS
WORK=$(mktemp -d /var/tmp/hapticrom-docker-test.XXXXXX)
chmod 0777 "$WORK"  # the containers' user (uid 1000) writes the mesh, solve and model here
CONTAINERS=()
cleanup() {
    local status=$?
    for c in "${CONTAINERS[@]}"; do buildah rm "$c" >/dev/null 2>&1 || true; done
    if [ "$KEEP" != 1 ]; then
        buildah rmi "$OFFLINE" "$RUNTIME" >/dev/null 2>&1 || true
        rm -rf "$WORK"
    else
        echo "kept: images $OFFLINE $RUNTIME, files in $WORK"
    fi
    echo "docker-test: $([ $status = 0 ] && echo passed || echo FAILED) in $((SECONDS - START)) s"
}
trap cleanup EXIT

section() { printf '\n== %s  [%d s]\n' "$*" $((SECONDS - START)); }
fail() { echo "docker-test: FAILED: $*" >&2; exit 1; }
container() {  # NAME IMAGE: a working container, removed at the end
    CONTAINERS+=("$1")
    buildah from --pull=never --name "$1" "$2" >/dev/null
}
run() { buildah run "${ISO[@]}" "$@"; }  # [OPTIONS] CONTAINER -- COMMAND..., as the image's user
show() { sed 's/^/   | /'; }

# Build output: the steps, with the seconds since the build started, and the key lines.
build() {  # WHICH (offline | runtime) TAG
    local t=$SECONDS log=$WORK/build-$1.log layers=()
    [ "$KEEP" = 1 ] && layers=(--layers)
    if ! buildah build "${ISO[@]}" --pull=never "${layers[@]}" --build-arg "BASE_IMAGE=$BASE" \
        -f "docker/Dockerfile.$1" -t "$2" . >"$log" 2>&1; then
        tail -n 40 "$log" | show
        fail "building docker/Dockerfile.$1"
    fi
    grep -E '^STEP |^Successfully installed|imports without dolfinx|^campaign done|^wrote .*model|^Successfully tagged' "$log" \
        | cut -c1-150 | show || true
    echo "   built $2 in $((SECONDS - t)) s"
}

section "base image $BASE"
if [ "${DOCKER_TEST_REBUILD_BASE:-0}" = 1 ] || ! buildah inspect --type image "$BASE" >/dev/null 2>&1; then
    t=$SECONDS
    docker/base.sh "$BASE" | show
    echo "   built in $((SECONDS - t)) s"
else
    echo "   cached (DOCKER_TEST_REBUILD_BASE=1 builds it again)"
fi

section "build docker/Dockerfile.runtime"
build runtime "$RUNTIME"
section "build docker/Dockerfile.offline"
build offline "$OFFLINE"

section "offline image: coarse cornea, solve and tiny campaign under mpirun -n 2"
cp docker/smoke-solve.toml docker/smoke-campaign.toml "$WORK/"
chmod a+r "$WORK"/*.toml
OFF=hapticrom-test-offline-$$
container "$OFF" "$OFFLINE"
user=$(run "$OFF" -- id -u)
echo "   user: $(run "$OFF" -- id)"
[ "$user" != 0 ] || fail "the offline image runs as root"
jit() { run "$OFF" -- sh -c 'ls "$XDG_CACHE_HOME"/fenics/*.so 2>/dev/null | wc -l'; }
jit_before=$(jit)
t=$SECONDS
run -v "$WORK:/data" "$OFF" -- hapticrom mesh cornea --refinement coarse --out /data/cornea-coarse.msh | show
echo "   mesh: $((SECONDS - t)) s"
t=$SECONDS
run -v "$WORK:/data" "$OFF" -- mpirun -n 2 hapticrom solve /data/smoke-solve.toml --out /data/solve \
    >"$WORK/solve.log" 2>&1 || { show <"$WORK/solve.log"; fail "solve"; }
tail -n 3 "$WORK/solve.log" | cut -c1-200 | show
echo "   solve (mpirun -n 2): $((SECONDS - t)) s"
t=$SECONDS
run -v "$WORK:/data" "$OFF" -- mpirun -n 2 hapticrom train /data/smoke-campaign.toml --out /data/model.h5 \
    >"$WORK/train.log" 2>&1 || { show <"$WORK/train.log"; fail "train"; }
grep -E '^campaign done|^global|^wrote' "$WORK/train.log" | cut -c1-200 | show
echo "   train (mpirun -n 2): $((SECONDS - t)) s"
jit_after=$(jit)
echo "   JIT cache: $jit_before compiled form modules before, $jit_after after"
[ "$jit_before" -gt 0 ] && [ "$jit_after" = "$jit_before" ] || fail "forms compiled at run time (JIT cache not warm)"
[ -s "$WORK/model.h5" ] || fail "no model"

section "runtime image: the model (host file $WORK/model.h5, mounted read only)"
RT=hapticrom-test-runtime-$$
container "$RT" "$RUNTIME"
user=$(run "$RT" -- id -u)
echo "   user: $(run "$RT" -- id)"
[ "$user" != 0 ] || fail "the runtime image runs as root"
if out=$(run "$RT" -- python -c "import dolfinx" 2>&1); then fail "dolfinx imports in the runtime image"; fi
echo "   import dolfinx: $(grep -o 'ModuleNotFoundError.*' <<<"$out")"
t=$SECONDS
run -v "$WORK:/data:ro" "$RT" -- hapticrom play /data/model.h5 --seconds 1 --free-running >"$WORK/play.log" 2>&1 \
    || { show <"$WORK/play.log"; fail "play"; }
tail -n 2 "$WORK/play.log" | show
echo "   play: $((SECONDS - t)) s"
t=$SECONDS
run -v "$WORK:/data:ro" "$RT" -- hapticrom bench /data/model.h5 --steps 20000 >"$WORK/bench.log" 2>&1 \
    || { show <"$WORK/bench.log"; fail "bench"; }
show <"$WORK/bench.log"
echo "   bench: $((SECONDS - t)) s"

# From before `buildah from` (a new container) to the first step_force's return, as the
# image runs it (its warm numba cache), then with an empty numba cache (what the image would
# cost without the build-time compilation).
FIRST_STEP='
import sys, time
t_py = time.time()
import numpy as np
import hapticrom.online
t_import = time.time()
model = hapticrom.online.load(sys.argv[1])
sim = model.simulator()
sim.set_contact(np.zeros(3))
x = sim.step_force(-0.5 * model.trained_force * sim.contact_normal)
t = time.time()
t0 = float(sys.argv[2])
print(f"{t - t0:.2f} s (container and Python start {t_py - t0:.2f} s, imports {t_import - t_py:.2f} s,"
      f" load and first step {t - t_import:.2f} s); tool displacement {x[2]:+.4f} mm")
'
first_step() {  # NAME [ENV=VALUE]: a new container's start to its first step
    local t0
    t0=$(date +%s.%N)
    container "$1" "$RUNTIME"
    run -v "$WORK:/data:ro" "$1" -- env ${2:+"$2"} python -c "$FIRST_STEP" /data/model.h5 "$t0"
}
section "runtime image: start to first step"
printf '   warm numba cache (as built):        '
first_step "hapticrom-test-first-$$"
printf '   empty numba cache (for comparison): '
first_step "hapticrom-test-cold-$$" NUMBA_CACHE_DIR=/tmp/numba-empty

section "image sizes"
buildah images --format '{{.Name}}:{{.Tag}}  {{.Size}}' | grep -E "hapticrom-(base|offline|runtime)" | show
