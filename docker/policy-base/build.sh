#!/usr/bin/env bash
# Build the base image for ManiEval policy images, localhost/manieval-base:bookworm: a minimal
# Debian bookworm with python3, numpy and msgpack (what the SDK needs) and a non-root user, made
# with debootstrap and `podman import` because no public image registry is reachable here.
#
# Cached: does nothing while `podman image exists` says the image is there (--force rebuilds).
# Needs root, debootstrap and podman (apt-get install -y debootstrap podman runc). About a
# minute the first time. Environment: MANIEVAL_BASE_IMAGE (the tag), DEBIAN_MIRROR.
set -euo pipefail

image=${MANIEVAL_BASE_IMAGE:-localhost/manieval-base:bookworm}
mirror=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
# The uid the docker executor runs policies as (worker/containers.py POLICY_UID).
policy_uid=65532
force=0
[ "${1:-}" = --force ] && force=1

for tool in debootstrap podman flock; do
  command -v "$tool" >/dev/null || { echo "build.sh: $tool is not installed" >&2; exit 1; }
done
[ "$(id -u)" = 0 ] || { echo "build.sh: debootstrap needs root" >&2; exit 1; }

# Two test sessions on one machine share podman's image store: build once.
mkdir -p /run/lock
exec 9>/run/lock/manieval-base.lock
flock 9

if [ "$force" = 0 ] && podman image exists "$image"; then
  exit 0
fi

rootfs=$(mktemp -d /var/tmp/manieval-base.XXXXXX)
trap 'rm -rf "$rootfs"' EXIT

echo "build.sh: debootstrap bookworm into $rootfs (about a minute)" >&2
debootstrap --variant=minbase --include=python3,python3-numpy,python3-msgpack \
  bookworm "$rootfs" "$mirror" >"$rootfs.log" 2>&1 || {
  tail -n 30 "$rootfs.log" >&2
  rm -f "$rootfs.log"
  exit 1
}
rm -f "$rootfs.log"

# A named, unprivileged user for policies; home is the container's tmpfs.
echo "policy:x:$policy_uid:$policy_uid:ManiEval policy:/tmp:/usr/sbin/nologin" >>"$rootfs/etc/passwd"
echo "policy:x:$policy_uid:" >>"$rootfs/etc/group"
echo "policy:!:19000::::::" >>"$rootfs/etc/shadow"

# What a policy never needs, and what only makes the image larger to push and pull.
rm -rf "$rootfs"/var/cache/apt/archives/*.deb "$rootfs"/var/lib/apt/lists/* \
  "$rootfs"/usr/share/doc/* "$rootfs"/usr/share/man/* "$rootfs"/usr/share/info/* \
  "$rootfs"/usr/share/locale/* "$rootfs"/var/log/*.log "$rootfs"/var/cache/debconf/*-old

tar --numeric-owner -C "$rootfs" -c . | podman import --quiet \
  --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
  --change 'ENV LANG=C.UTF-8' \
  --change 'CMD ["python3"]' \
  --message "manieval policy base: debootstrap bookworm minbase + python3-numpy + python3-msgpack" \
  - "$image" >/dev/null
echo "build.sh: built $image" >&2
