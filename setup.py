"""Map the top-level folders onto the ``burrforce`` import namespace.

``server/`` → ``burrforce.server``, ``client/`` → ``burrforce.client``, ``proto/`` →
``burrforce.proto``. Works for ``pip install .`` and ``pip install -e .``.
"""

from setuptools import find_packages, setup

TOP_LEVEL = ("server", "client", "proto")

packages = []
package_dir = {}
for top in TOP_LEVEL:
    package_dir[f"burrforce.{top}"] = top
    packages.append(f"burrforce.{top}")
    packages += [f"burrforce.{top}.{sub}" for sub in find_packages(top)]

setup(
    packages=packages,
    package_dir=package_dir,
    package_data={"burrforce.proto": ["*.md", "vectors/*"]},
)
