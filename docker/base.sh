#!/usr/bin/env bash
# A local stand-in for python:3.12-slim-bookworm, for machines that cannot reach a container
# registry (`make docker-test`): a Debian bookworm root file system from debootstrap, plus a
# Python 3.12 built for bookworm (pyenv's) copied to /usr/local, committed as a buildah image.
#   docker/base.sh [IMAGE]            (root; needs buildah and debootstrap)
# Environment: PYTHON312 (a python3.12 whose prefix is copied; default: pyenv's newest 3.12),
# DEBIAN_MIRROR / DEBIAN_SECURITY_MIRROR (default: those the host's apt sources name).
set -euo pipefail

IMAGE=${1:-localhost/hapticrom-base:3.12-bookworm}

# The Python: its prefix (sys.base_prefix), which must be a self-contained installation.
if [ -z "${PYTHON312:-}" ]; then
    PYTHON312=$(ls -d "${PYENV_ROOT:-$HOME/.pyenv}"/versions/3.12*/bin/python3.12 2>/dev/null | sort -V -r | head -n 1)
fi
[ -n "$PYTHON312" ] || { echo "base.sh: no Python 3.12 (set PYTHON312=/path/to/python3.12)" >&2; exit 1; }
PREFIX=$("$PYTHON312" -c 'import sys; assert sys.version_info[:2] == (3, 12); print(sys.base_prefix)')
case "$PREFIX" in
    /usr | /usr/local) echo "base.sh: $PYTHON312 is a system Python ($PREFIX); give a pyenv-style one" >&2; exit 1 ;;
esac

# The mirrors the host's apt sources name (one-line or deb822 format).
sources() { cat /etc/apt/sources.list /etc/apt/sources.list.d/*.list /etc/apt/sources.list.d/*.sources 2>/dev/null || true; }
uri() { sources | grep -v '^[[:space:]]*#' | grep -oE "(https?|ftp)://[^ ]*/$1/?( |$)" | head -n 1 | tr -d ' ' | sed 's#/$##'; }
MIRROR=${DEBIAN_MIRROR:-$(uri debian)}
MIRROR=${MIRROR:-http://deb.debian.org/debian}
SECURITY=${DEBIAN_SECURITY_MIRROR:-$(uri debian-security)}
SECURITY=${SECURITY:-http://deb.debian.org/debian-security}

WORK=$(mktemp -d /var/tmp/hapticrom-base.XXXXXX)
CTR=
cleanup() {
    if [ -n "$CTR" ]; then buildah rm "$CTR" >/dev/null 2>&1 || true; fi
    rm -rf "$WORK"
}
trap cleanup EXIT
ROOT=$WORK/rootfs

echo "base.sh: debootstrap bookworm from $MIRROR; Python $PREFIX -> /usr/local"
# What the official image's Python links (ssl, ctypes, sqlite3, lzma, bz2, readline, uuid,
# expat), and CA certificates for pip.
debootstrap --variant=minbase \
    --include=ca-certificates,netbase,tzdata,libssl3,libffi8,libsqlite3-0,libbz2-1.0,liblzma5,zlib1g,libncursesw6,libreadline8,libuuid1,libexpat1 \
    bookworm "$ROOT" "$MIRROR" >"$WORK/debootstrap.log" 2>&1 \
    || { tail -n 20 "$WORK/debootstrap.log" >&2; exit 1; }
rm -f "$ROOT/etc/apt/sources.list"
cat >"$ROOT/etc/apt/sources.list.d/debian.sources" <<EOF
Types: deb
URIs: $MIRROR
Suites: bookworm bookworm-updates
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg

Types: deb
URIs: $SECURITY
Suites: bookworm-security
Components: main
Signed-By: /usr/share/keyrings/debian-archive-keyring.gpg
EOF

# The Python, without its test suite, Tk, static library and installed packages (pip comes
# afresh from ensurepip); the scripts and build configuration are moved to /usr/local.
tar -C "$PREFIX" -c \
    --exclude=./lib/python3.12/test --exclude=./lib/python3.12/idlelib \
    --exclude=./lib/python3.12/tkinter --exclude=./lib/python3.12/turtledemo \
    --exclude='./lib/python3.12/lib-dynload/_tkinter*' --exclude='./lib/python3.12/site-packages/*' \
    --exclude='./lib/python3.12/config-3.12-*/*.a' --exclude='./bin/idle*' --exclude='./bin/pip*' \
    --exclude='./bin/2to3*' --exclude='./bin/pydoc*' --exclude='./bin/*-gdb.py' . \
    | tar -C "$ROOT/usr/local" -x --no-same-owner
grep -rlI --null -F "$PREFIX" "$ROOT/usr/local" | xargs -0 -r sed -i "s#$PREFIX#/usr/local#g"
find "$ROOT/usr/local/lib/python3.12" -name '_sysconfigdata*.pyc' -delete
# Certificate authorities the host added to Debian's (a TLS-inspecting proxy's, say): pip in
# the images reaches PyPI only if they trust what the host trusts.
if [ -f /etc/ssl/certs/ca-certificates.crt ]; then
    "$PYTHON312" - "$ROOT" <<'PY'
import pathlib, re, sys
pem = re.compile(r"-----BEGIN CERTIFICATE-----.+?-----END CERTIFICATE-----", re.S)
root = pathlib.Path(sys.argv[1])
have = {"".join(c.split()) for c in pem.findall((root / "etc/ssl/certs/ca-certificates.crt").read_text())}
host = pem.findall(pathlib.Path("/etc/ssl/certs/ca-certificates.crt").read_text())
extra = [c for c in host if "".join(c.split()) not in have]
for i, c in enumerate(extra):
    (root / f"usr/local/share/ca-certificates/host-{i}.crt").write_text(c + "\n")
print(f"base.sh: {len(extra)} CA certificate(s) of the host added to the image's")
PY
fi
# pip: the constraints file's (a recent pip, as in the official image, which also uses the
# system's certificate store); ensurepip's bundled one first.
cp "$(dirname "$0")/../constraints.txt" "$ROOT/tmp/constraints.txt"
chroot "$ROOT" /usr/bin/env -i PATH=/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin HOME=/root PIP_ROOT_USER_ACTION=ignore /bin/sh -euc '
    ldconfig
    out=$(update-ca-certificates 2>&1) || { echo "$out" >&2; exit 1; }
    out=$(python3.12 -m ensurepip --default-pip 2>&1) || { echo "$out" >&2; exit 1; }
    python3 -m pip install --quiet --no-cache-dir --cert /etc/ssl/certs/ca-certificates.crt \
        --constraint /tmp/constraints.txt --upgrade pip
    python3 -c "import ssl, ctypes, sqlite3, lzma, bz2, zlib, readline, uuid, pyexpat, sysconfig; print(\"base: Python\", sysconfig.get_python_version(), sysconfig.get_paths()[\"include\"])"
    pip --version
'
rm -rf "$ROOT"/var/lib/apt/lists/* "$ROOT"/var/cache/apt/*.bin "$ROOT"/var/cache/apt/archives/*.deb \
    "$ROOT"/var/log/* "$ROOT"/root/.cache "$ROOT"/tmp/constraints.txt "$ROOT"/etc/hostname "$ROOT"/etc/resolv.conf

# The root file system as an image (no registry, no import tarball: buildah mounts and copies).
CTR=$(buildah from scratch)
MNT=$(buildah mount "$CTR")
tar -C "$ROOT" -c --exclude='./dev/*' --exclude='./proc/*' --exclude='./sys/*' . | tar -C "$MNT" -xp
buildah umount "$CTR" >/dev/null
buildah config --env PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin \
    --env LANG=C.UTF-8 --cmd python3 --os linux --arch "$(dpkg --print-architecture)" \
    --label org.opencontainers.image.description="hapticrom local base: debootstrap bookworm + $("$PYTHON312" -V)" \
    "$CTR"
buildah commit --quiet --rm "$CTR" "$IMAGE" >/dev/null
CTR=
echo "base.sh: built $IMAGE"
