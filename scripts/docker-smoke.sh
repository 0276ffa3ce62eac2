#!/usr/bin/env bash
# Build the Docker image from the Dockerfile (unmodified) and run it, without a Docker engine
# and without pulling any image: podman + buildah from Debian, run as root. Called by .ci/run
# after the test suite; docs/deployment.md describes what it checks.
#
#   1. tools: podman, buildah, runc, conmon, mmdebstrap (apt-get install when missing); all
#      container state (storage, configs, runtime dirs) lives in one mktemp folder;
#   2. base images: a minimal Debian (mmdebstrap, from the host's apt sources) with python3 in
#      a venv stands in for python:3.11-slim; the same rootfs plus the host's node + npm for
#      node:20-bookworm-slim;
#   3. `buildah bud` of the Dockerfile; prints the image size;
#   4. one container (the image's own CMD and HEALTHCHECK): /healthz, a slow-header client cut
#      off with 408 after FFS_HEADER_TIMEOUT, a slow-body client cut off with the 408
#      body-timeout problem after FFS_BODY_TIMEOUT (5 s here), reconstructions (JSON,
#      PARDISO on noisy forms), a GLB the Khronos validator accepts, the web page and its
#      vendored three.js modules (scripts/docker_smoke_single.py);
#   5. the docker-compose.yml topology from the same image: scheduler, two workers, two API
#      replicas; a job submitted through one replica is polled and fetched through the other,
#      a deformation session created through one is dragged through the other; with API
#      keys: 401s, another key's job and session 404 (HTTP and WebSocket), a key's session
#      quota 429, a signed webhook retried after a 500, no key in the logs
#      (scripts/docker_smoke_compose.py; the tools: scripts/docker_smoke.py).
# Every container and image it made is removed on exit (trap), with the whole work folder
# (FFS_SMOKE_KEEP=1 keeps them for debugging: export the CONTAINERS_* variables it prints).
# Exit status: 0 = all checks passed, or skipped where no container can run here at all (not
# Linux, not root, no CAP_SYS_ADMIN, no apt-get, no python3; printed as SKIPPED: <why>);
# non-zero = a step failed (printed as FAILED: <step>, with the end of its log).
set -euo pipefail

ROOT=$(cd "$(dirname "$0")/.." && pwd)
IMAGE=localhost/fundamental-forms-service:0.1.0
START=$SECONDS

log() { printf 'docker-smoke [%4ds]: %s\n' "$((SECONDS - START))" "$*"; }
skip() { log "SKIPPED: $*"; exit 0; }
fail() { log "FAILED: $*"; exit 1; }

[ "$(uname -s)" = Linux ] || skip "needs Linux (podman, buildah, mmdebstrap)"
[ "$(id -u)" = 0 ] || skip "needs root (builds the base images with mmdebstrap, runs podman as root)"
command -v apt-get > /dev/null || skip "needs apt-get (Debian/Ubuntu) to install podman and buildah"
command -v python3 > /dev/null || skip "needs python3 on the host (the checks use only its standard library)"
# CAP_SYS_ADMIN (bit 21): mounts, namespaces. Without it (e.g. an unprivileged container) no
# container can run here at all.
cap_eff=$(awk '/^CapEff:/ {print $2}' /proc/self/status)
(( (16#${cap_eff:-0} >> 21) & 1 )) || skip "needs CAP_SYS_ADMIN to run containers (CapEff=$cap_eff)"

# -- 1. tools and a private container configuration ------------------------------------------
need=()
for tool in podman buildah runc conmon mmdebstrap; do
  command -v "$tool" > /dev/null || need+=("$tool")
done
[ -d /usr/lib/cni ] || need+=(containernetworking-plugins)
command -v node > /dev/null && command -v npm > /dev/null || need+=(nodejs npm)
if [ "${#need[@]}" -gt 0 ]; then
  log "apt-get install ${need[*]}"
  apt-get update -qq
  DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${need[@]}" \
    > /dev/null
fi

# The one file outside the work folder: containers/image's blob-info cache (root's is always
# /var/lib/containers/cache). Removed on exit unless it was there before.
BLOB_CACHE=/var/lib/containers/cache/blob-info-cache-v1.boltdb
[ -e "$BLOB_CACHE" ] && had_blob_cache=1 || had_blob_cache=
WORK=$(mktemp -d "${TMPDIR:-/var/tmp}/ffs-docker-smoke.XXXXXX")
export CONTAINERS_STORAGE_CONF=$WORK/storage.conf
export CONTAINERS_CONF=$WORK/containers.conf
export CONTAINERS_REGISTRIES_CONF=$WORK/registries.conf
export XDG_RUNTIME_DIR=$WORK/xdg TMPDIR=$WORK/tmp
mkdir -p "$WORK/tmp" "$WORK/xdg" "$WORK/run" "$WORK/storage"

cleanup() {
  status=$?
  trap - EXIT INT TERM
  if [ -n "${FFS_SMOKE_KEEP:-}" ]; then
    log "FFS_SMOKE_KEEP set: kept $WORK (exit $status); to inspect: export CONTAINERS_STORAGE_CONF=$CONTAINERS_STORAGE_CONF CONTAINERS_CONF=$CONTAINERS_CONF CONTAINERS_REGISTRIES_CONF=$CONTAINERS_REGISTRIES_CONF"
    exit "$status"
  fi
  if [ -f "$CONTAINERS_STORAGE_CONF" ]; then
    podman rm --all --force --time 2 > /dev/null 2>&1 || true
    podman rmi --all --force > /dev/null 2>&1 || true
    buildah rm --all > /dev/null 2>&1 || true
    podman system prune --all --force > /dev/null 2>&1 || true
  fi
  # Whatever is still mounted below the work folder (overlay layers, shm), deepest first.
  awk -v w="$WORK" 'index($2, w) == 1 {print $2}' /proc/mounts | sort -r | while read -r m; do
    umount -l "$m" 2> /dev/null || true
  done
  rm -rf "$WORK"
  if [ -z "$had_blob_cache" ]; then
    rm -f "$BLOB_CACHE"
    rmdir "$(dirname "$BLOB_CACHE")" /var/lib/containers 2> /dev/null || true
  fi
  if [ "$status" = 0 ]; then
    log "PASSED in $((SECONDS - START)) s (work folder removed)"
  else
    log "FAILED (exit $status) after $((SECONDS - START)) s; containers, images and $WORK removed"
  fi
  exit "$status"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

# Native overlayfs when the kernel mounts it on this filesystem, else the (slower) vfs driver.
driver=vfs
mkdir -p "$WORK/probe/l" "$WORK/probe/u" "$WORK/probe/w" "$WORK/probe/m"
if mount -t overlay overlay -o "lowerdir=$WORK/probe/l,upperdir=$WORK/probe/u,workdir=$WORK/probe/w" \
    "$WORK/probe/m" 2> /dev/null; then
  umount "$WORK/probe/m"
  driver=overlay
fi
rm -rf "$WORK/probe"
cat > "$CONTAINERS_STORAGE_CONF" << EOF
[storage]
driver = "$driver"
graphroot = "$WORK/storage"
runroot = "$WORK/run"
EOF
# crun refuses this kind of host's cgroup layout: runc with cgroupfs. Root may lack
# CAP_SYS_RESOURCE, so the default rlimits are set explicitly within the current ones.
nofile=$(ulimit -Hn)
nproc=$(ulimit -Hu)
pid_max=$(cat /proc/sys/kernel/pid_max)
if [ "$nproc" = unlimited ] || [ "$nproc" -gt "$pid_max" ]; then nproc=$pid_max; fi
[ "$nofile" = unlimited ] && nofile=1048576
cat > "$CONTAINERS_CONF" << EOF
[containers]
default_ulimits = ["nofile=$nofile:$nofile", "nproc=$nproc:$nproc"]
log_driver = "k8s-file"
[engine]
runtime = "runc"
cgroup_manager = "cgroupfs"
events_logger = "file"
events_logfile_path = "$WORK/events.log"
tmp_dir = "$WORK/libpod"
volume_path = "$WORK/volumes"
[network]
network_config_dir = "$WORK/cni"
EOF
cat > "$CONTAINERS_REGISTRIES_CONF" << 'EOF'
unqualified-search-registries = ["docker.io"]
short-name-mode = "permissive"
EOF
echo '{"default": [{"type": "insecureAcceptAnything"}]}' > "$WORK/policy.json"
podman info > /dev/null || fail "podman does not start (podman info)"
log "tools ready: $(podman --version), $(buildah --version | cut -d' ' -f1-3), storage driver $driver"

# -- 2. stand-ins for the base images -----------------------------------------------------------
# The host's own apt sources (whatever mirror it must use) build the rootfs; inside the rootfs
# Debian's public default is written instead.
codename=$(. /etc/os-release && echo "${VERSION_CODENAME:-bookworm}")
sources=()
if [ -s /etc/apt/sources.list.d/debian.sources ]; then
  sources=(/etc/apt/sources.list.d/debian.sources)
elif grep -qs '^deb ' /etc/apt/sources.list; then
  sources=(/etc/apt/sources.list)
fi
rootfs=$WORK/rootfs
cat > "$WORK/debian.sources" << EOF
Types: deb
URIs: http://deb.debian.org/debian
Suites: $codename $codename-updates
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg

Types: deb
URIs: http://deb.debian.org/debian-security
Suites: $codename-security
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
EOF
log "mmdebstrap $codename (essential + apt) + python3, python3-venv, ca-certificates, passwd"
slim=(--dpkgopt='path-exclude=/usr/share/doc/*' --dpkgopt='path-include=/usr/share/doc/*/copyright'
  --dpkgopt='path-exclude=/usr/share/man/*' --dpkgopt='path-exclude=/usr/share/info/*'
  --dpkgopt='path-exclude=/usr/share/locale/*' --dpkgopt='path-include=/usr/share/locale/locale.alias'
  --dpkgopt='path-exclude=/usr/share/lintian/*')
mmdebstrap --quiet --variant=apt "${slim[@]}" --include=python3,python3-venv,ca-certificates,passwd \
  --customize-hook='chroot "$1" python3 -m venv /opt/venv' \
  --customize-hook='rm -f "$1"/etc/apt/sources.list "$1"/etc/apt/sources.list.d/*' \
  --customize-hook="copy-in $WORK/debian.sources /etc/apt/sources.list.d/" \
  "$codename" "$rootfs" "${sources[@]}" > "$WORK/mmdebstrap.log" 2>&1 \
  || { tail -n 30 "$WORK/mmdebstrap.log"; fail "mmdebstrap"; }
log "rootfs ready ($(du -sm "$rootfs" | cut -f1) MB); podman import"
pip_ca=$(chroot "$rootfs" /opt/venv/bin/python -c \
  'from pip._vendor import certifi; print(certifi.where())' 2> /dev/null || true)
path=/opt/venv/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
tar -C "$rootfs" -cf - . | podman import --quiet --change "ENV PATH=$path" \
  --change "ENV LANG=C.UTF-8" --change 'CMD ["python3"]' - docker.io/library/python:3.11-slim \
  > /dev/null || fail "podman import python:3.11-slim"
# node + npm: the host's node binary and npm package folder when they run in the rootfs
# (e.g. NodeSource's self-contained node), else Debian's nodejs + npm in a rootfs of their own.
node_bin=$(readlink -f "$(command -v node)")
npm_dir=$(cd "$(dirname "$(readlink -f "$(command -v npm)")")/.." && pwd)
mkdir -p "$rootfs/usr/local/bin" "$rootfs/usr/local/lib/node_modules"
cp "$node_bin" "$rootfs/usr/local/bin/node"
cp -a "$npm_dir" "$rootfs/usr/local/lib/node_modules/npm"
ln -s ../lib/node_modules/npm/bin/npm-cli.js "$rootfs/usr/local/bin/npm"
ln -s ../lib/node_modules/npm/bin/npx-cli.js "$rootfs/usr/local/bin/npx"
if ! chroot "$rootfs" /usr/local/bin/npm --version > /dev/null 2>&1; then
  log "the host's node does not run in the stand-in rootfs: Debian's nodejs + npm instead"
  mmdebstrap --quiet --variant=apt "${slim[@]}" --include=nodejs,npm,ca-certificates \
    "$codename" "$WORK/rootfs-node" "${sources[@]}" > "$WORK/mmdebstrap.log" 2>&1 \
    || { tail -n 30 "$WORK/mmdebstrap.log"; fail "mmdebstrap (node)"; }
  rm -rf "$rootfs" && rootfs=$WORK/rootfs-node
fi
chroot "$rootfs" npm --version > /dev/null || fail "npm does not run in the node rootfs"
tar -C "$rootfs" -cf - . | podman import --quiet --change "ENV PATH=$path" \
  --change "ENV NODE_EXTRA_CA_CERTS=/etc/ssl/certs/ca-certificates.crt" \
  --change 'CMD ["node"]' - docker.io/library/node:20-bookworm-slim > /dev/null \
  || fail "podman import node:20-bookworm-slim"
rm -rf "$WORK/rootfs" "$WORK/rootfs-node"
log "base images: python:3.11-slim $(podman image inspect --format '{{.Size}}' python:3.11-slim \
  | awk '{printf "%.0f MB", $1 / 1e6}'), node:20-bookworm-slim (stand-ins)"

# -- 3. the image, from the Dockerfile unmodified ------------------------------------------------
# RUN steps reach the registries as the host does: the host's CA bundle is bind-mounted (read
# only) over the image's bundle and over the one pip vendors; nothing of that stays in the image.
ca=/etc/ssl/certs/ca-certificates.crt
mounts=()
if [ -s "$ca" ]; then
  mounts+=(--volume "$ca:$ca:ro")
  [ -z "$pip_ca" ] || mounts+=(--volume "$ca:$pip_ca:ro")
fi
log "buildah bud (Dockerfile unmodified)"
buildah bud --pull=never --format docker --isolation oci --network host --layers=false \
  --signature-policy "$WORK/policy.json" "${mounts[@]}" --tag "$IMAGE" \
  --file "$ROOT/Dockerfile" "$ROOT" > "$WORK/build.log" 2>&1 \
  || { tail -n 40 "$WORK/build.log"; fail "image build (buildah bud)"; }
grep -E '^prune_mkl:' "$WORK/build.log" | cut -c1-300 | sed 's/^/    /' || true
size=$(podman image inspect --format '{{.Size}}' "$IMAGE")
base=$(podman image inspect --format '{{.Size}}' docker.io/library/python:3.11-slim)
log "image built: $IMAGE, $((size / 1000000)) MB = base $((base / 1000000)) MB + \
$(((size - base) / 1000000)) MB of the Dockerfile's layers"

# -- 4./5. the containers ------------------------------------------------------------------------
python3 "$ROOT/scripts/docker_smoke_single.py" --image "$IMAGE" --root "$ROOT" \
  || fail "single container checks"
python3 "$ROOT/scripts/docker_smoke_compose.py" --image "$IMAGE" --root "$ROOT" \
  || fail "compose topology checks"
