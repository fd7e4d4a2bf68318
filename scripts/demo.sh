#!/usr/bin/env bash
# Placeholder: the end-to-end demo (simulate -> build map -> evaluate) replaces this file.
set -euo pipefail
echo "demo not yet available" >&2
exit 1
