"""handedit: egocentric human-hand video -> paired robot-hand images (domain library).

Pure domain code: functions take arrays and configs and return arrays and results.
Nothing in this package imports Prefect; orchestration lives in ``tasks/`` and ``flows/``.
"""

__version__ = "0.1.0"
