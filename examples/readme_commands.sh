#!/bin/sh
# README's "Useful commands", in order, exactly as written there (comments dropped; its first
# line activates .venv, which make made); run it from the repository's root:
#   sh examples/readme_commands.sh
set -e; here="$(dirname "$0")"; export PATH="$here/../.venv/bin:$PATH"; awk '/^## Useful commands/{f=1} f&&/^```sh/{b=1;next} b&&/^```/{exit} b' "$here/../README.md" | sed 's/  *# .*$//' | sh -ex
