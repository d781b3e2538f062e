"""One import namespace: the design card's top-level folders install as subpackages.

``flows/`` -> ``handedit.flows``, ``tasks/`` -> ``handedit.tasks``, ``storage/`` ->
``handedit.storage``, ``dashboards/`` -> ``handedit.dashboards``, beside the domain library
in ``handedit/``. Nothing generic lands in site-packages, so a Dask worker's scratch folder
(whose spill directory is named ``storage/``) can never shadow a project package, and both
``pip install .`` and the default (strict) ``pip install -e .`` run the flow. Everything
else is in pyproject.toml; this file only computes the package map, so a new subpackage
needs no edit here.
"""

from setuptools import find_packages, setup

FOLDERS = {"handedit": "handedit", "handedit.flows": "flows", "handedit.tasks": "tasks",
           "handedit.storage": "storage", "handedit.dashboards": "dashboards"}

packages = [name for pkg, folder in FOLDERS.items() for name in (pkg, *(f"{pkg}.{p}" for p in find_packages(folder)))]
setup(packages=packages, package_dir=FOLDERS)
