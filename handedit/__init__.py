"""handedit: egocentric human-hand video -> paired robot-hand images (domain library).

Pure domain code: functions take arrays and configs and return arrays and results.
Nothing in this package imports Prefect; orchestration lives in ``tasks/`` and ``flows/``.
"""

__version__ = "0.1.0"

# Run from a source checkout with a non-editable install, ``import handedit`` finds this
# folder first; extend_path adds the installed copy, which holds the subpackages that
# setup.py maps from the top-level folders (flows, tasks, storage, dashboards).
__path__ = __import__("pkgutil").extend_path(__path__, __name__)
