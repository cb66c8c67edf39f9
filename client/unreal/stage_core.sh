#!/bin/sh
# SPDX-License-Identifier: MIT
# Copyright (c) 2026 the burrforce authors
#
# Copies the header-only core (client/cpp/include) into the plugin's ThirdParty folder, as a
# release does, so the plugin folder can be copied into a project on its own. The copy is
# not kept in git (one source of truth: client/cpp/include).
set -eu
here=$(cd "$(dirname "$0")" && pwd)
dest="$here/BurrforceHaptics/Source/ThirdParty/burrforce/include"
rm -rf "$dest"
mkdir -p "$dest"
cp -R "$here/../cpp/include/burrforce" "$dest/"
echo "staged the burrforce core into $dest"
