"""The HandEdit benchmark (paper sec. "HandEdit Benchmark", "Experimental Setup").

- ``testset``: the two tracks, item selection, the URDF-reference-conditioned instruction;
- ``manifest``: the authors' toolkit JSONL manifest (one object per line);
- ``editors``: editor adapters (OpenAI-compatible image-edit HTTP API, command line);
- ``prices``: the paper's roster prices per 1k images (cost accounting);
- ``report``: per-track tables (Markdown, LaTeX, CSV) and radar charts (OpenCV).

Folder I/O is ``storage.benchmark``; orchestration is ``flows.benchmark`` / ``flows.evaluate``.
"""
