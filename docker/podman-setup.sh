#!/usr/bin/env bash
# One-time Podman setup for a worker running the docker executor (as root), idempotent:
#   docker/podman-setup.sh          install docker/containers.conf as a containers.conf drop-in
#   docker/podman-setup.sh --serve  also start Podman's Docker-API service unless it answers
# The socket is $MANIEVAL_ENGINE_SOCKET (default /run/manieval/podman.sock, the executor's
# default engine URL). Needs: apt-get install -y podman runc.
set -euo pipefail

here=$(cd "$(dirname "$0")" && pwd)
socket=${MANIEVAL_ENGINE_SOCKET:-/run/manieval/podman.sock}
dropin=/etc/containers/containers.conf.d/50-manieval.conf

[ "$(id -u)" = 0 ] || { echo "podman-setup.sh: run as root" >&2; exit 1; }
for tool in podman runc; do
  command -v "$tool" >/dev/null || {
    echo "podman-setup.sh: $tool is missing: apt-get install -y podman runc" >&2
    exit 1
  }
done

if ! cmp -s "$here/containers.conf" "$dropin"; then
  install -D -m 0644 "$here/containers.conf" "$dropin"
  echo "podman-setup.sh: installed $dropin" >&2
fi

[ "${1:-}" = --serve ] || exit 0

if podman --remote --url "unix://$socket" version >/dev/null 2>&1; then
  exit 0
fi
install -d -m 0700 "$(dirname "$socket")"
rm -f "$socket"
# cwd: Podman 4's conmon drops an "oom" file into its working directory.
cd "$(dirname "$socket")"
nohup podman system service --time=0 "unix://$socket" >/var/log/manieval-podman.log 2>&1 &
for _ in $(seq 100); do
  if podman --remote --url "unix://$socket" version >/dev/null 2>&1; then
    echo "podman-setup.sh: Docker API on unix://$socket" >&2
    exit 0
  fi
  sleep 0.1
done
echo "podman-setup.sh: the service did not answer; see /var/log/manieval-podman.log" >&2
exit 1
