#!/usr/bin/env bash
# Install the system packages ManiEval needs (Debian/Ubuntu), or say the one command to run.
# Fast when everything is present: it only asks dpkg. See ../shared/PLATFORM_NOTES.md for why
# each package is here. With --evaluator, only what `manieval evaluate` needs (a participant
# scoring a policy locally: `make install-evaluator`), not the service's nor its tests'.
set -euo pipefail

evaluator_only=0
[ "${1:-}" = --evaluator ] && evaluator_only=1

missing=()
need_backports=0

version_of() { dpkg-query -W -f='${Version}' "$1" 2>/dev/null || true; }

# SAPIEN needs a Vulkan device even for state observations; on CPU-only machines that is Mesa's
# lavapipe, 24.3 or newer (bookworm's own 22.3 lacks VK_KHR_external_semaphore_fd).
mesa=$(version_of mesa-vulkan-drivers)
if [ -z "$mesa" ] || dpkg --compare-versions "$mesa" lt 24.3; then
  missing+=(mesa-vulkan-drivers libvulkan1)
  need_backports=1
fi
python3 -c 'import ensurepip, venv' 2>/dev/null || missing+=(python3-venv)
# Local policies (`manieval evaluate --policy`, the demo's local: policies) run under bubblewrap;
# as root the sandbox is entered through util-linux's unshare and setpriv, and mount.
command -v bwrap >/dev/null || missing+=(bubblewrap)
command -v setpriv >/dev/null || missing+=(util-linux)
command -v mount >/dev/null || missing+=(mount)
if [ "$evaluator_only" = 0 ]; then
# The tests pin image tags to digests against a real OCI registry (CNCF distribution).
command -v docker-registry >/dev/null || missing+=(docker-registry)
# The worker tests run real Celery workers against a private redis-server they start.
command -v redis-server >/dev/null || missing+=(redis-server)
# Policy containers: Podman (its Docker API) with runc; debootstrap builds the base image.
command -v podman >/dev/null || missing+=(podman)
[ -x /usr/sbin/runc ] || missing+=(runc)
command -v debootstrap >/dev/null || missing+=(debootstrap)
# `manieval serve` and the demo publish that base in their registry with skopeo.
command -v skopeo >/dev/null || missing+=(skopeo)
command -v openssl >/dev/null || missing+=(openssl)  # signs the test registry's tokens
# Browser tests drive Debian's Chromium through Playwright (no browser download needed).
[ -x /usr/bin/chromium ] || missing+=(chromium)
# The deployment tests render the kustomize overlays with kubectl's embedded kustomize.
command -v kubectl >/dev/null || missing+=(kubernetes-client)
fi

[ ${#missing[@]} -eq 0 ] && exit 0

codename=$(. /etc/os-release && echo "${VERSION_CODENAME:-}")
apt_target=()
if [ "$need_backports" = 1 ] && [ "$codename" = bookworm ]; then
  apt_target=(-t bookworm-backports)
fi
install_cmd="apt-get install -y ${apt_target[*]} ${missing[*]}"

if [ "$(id -u)" != 0 ]; then
  echo "ManiEval needs system packages: ${missing[*]}" >&2
  if [ ${#apt_target[@]} -gt 0 ]; then
    echo "Run as root: echo 'deb http://deb.debian.org/debian bookworm-backports main'" \
      "> /etc/apt/sources.list.d/backports.list && apt-get update && $install_cmd" >&2
  else
    echo "Run as root: apt-get update && $install_cmd" >&2
  fi
  exit 1
fi

echo "Installing system packages: ${missing[*]}"
if [ ${#apt_target[@]} -gt 0 ] && [ ! -f /etc/apt/sources.list.d/backports.list ]; then
  echo "deb http://deb.debian.org/debian bookworm-backports main" \
    > /etc/apt/sources.list.d/backports.list
fi
apt-get update -q
DEBIAN_FRONTEND=noninteractive $install_cmd -q
