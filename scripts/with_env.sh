#!/usr/bin/env bash
# Run a command inside the built workspace: scripts/with_env.sh pytest test
source "$(dirname "${BASH_SOURCE[0]}")/env.sh"
exec "$@"
