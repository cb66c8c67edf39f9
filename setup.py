"""Map the top-level folders onto the ``burrforce`` import namespace.

``server/`` → ``burrforce.server``, ``client/`` → ``burrforce.client``, ``proto/`` →
``burrforce.proto``. Works for ``pip install .`` and ``pip install -e .``.

Every build (wheel, install, editable install) first fetches the live view's third-party files
from npm into ``server/ui/vendor/`` and verifies them against ``server/ui/vendor.lock.json``
(``server/ui/vendor.py``); a failed fetch fails the build. Already verified files are kept, so
a rebuild is offline. ``BURRFORCE_NPM_REGISTRY`` names a mirror.
"""

import importlib.util
import sys
from pathlib import Path

from setuptools import find_packages, setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent
TOP_LEVEL = ("server", "client", "proto")


def _load_ui_vendor():
    # By path: burrforce is not importable while it is being built, and vendor.py is stdlib only.
    spec = importlib.util.spec_from_file_location("_burrforce_ui_vendor",
                                                  ROOT / "server" / "ui" / "vendor.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


ui_vendor = _load_ui_vendor()


class BuildPyWithUiVendor(build_py):
    """build_py that fetches the live view's vendor files first.

    Editable installs run build_py too (in editable mode, where setuptools' own copy step is
    skipped): the fetch writes into the source tree, which is what an editable install serves.
    """

    def run(self):
        try:
            ui_vendor.fetch(ui_vendor.VENDOR_DIR)
        except ui_vendor.VendorError as exc:
            # SystemExit, not an Exception: editable_wheel turns an Exception raised by a
            # customised build_py into a warning and would install a page without its scripts.
            raise SystemExit(f"error: {exc}") from exc
        super().run()


packages = []
package_dir = {}
for top in TOP_LEVEL:
    package_dir[f"burrforce.{top}"] = top
    packages.append(f"burrforce.{top}")
    packages += [f"burrforce.{top}.{sub}" for sub in find_packages(top)]

# The wheel takes exactly the locked vendor files (not whatever else a folder holds).
ui_files = ["vendor.lock.json", "index.html"]
ui_files += [f"vendor/{entry['to']}" for pkg in ui_vendor.load_lock() for entry in pkg["files"]]
ui_files += [f"static/**/*.{ext}" for ext in ("html", "js", "css", "svg")]

setup(
    packages=packages,
    package_dir=package_dir,
    package_data={"burrforce.proto": ["*.md", "vectors/*"], "burrforce.server.ui": ui_files},
    cmdclass={"build_py": BuildPyWithUiVendor},
)
