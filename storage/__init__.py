"""storage: the Zarr v3 layout, chunk I/O, provenance and the rejection ledger.

One package owns paths and schemas (``storage.layout``); nothing else builds store
paths by hand. The store opens with plain ``zarr``, ``dask.array`` and ``xarray``.
"""

from handedit.storage.layout import SCOPES, Unit, chunk_ranges, stage_arrays, stage_names
from handedit.storage.ledger import read_ledger, status_counts
from handedit.storage.provenance import ChunkRecord, is_current, provenance_key, read_records, write_records
from handedit.storage.location import Location
from handedit.storage.store import (
    StoreError,
    create_or_open_store,
    create_unit,
    digest,
    open_store,
    read_chunk,
    set_attrs,
    writable,
    write_chunk,
)

__all__ = [
    "SCOPES", "Unit", "stage_arrays", "stage_names", "chunk_ranges", "read_ledger", "status_counts",
    "ChunkRecord", "is_current", "provenance_key", "read_records",
    "write_records", "StoreError", "create_or_open_store", "create_unit", "digest",
    "open_store", "read_chunk", "writable", "write_chunk", "Location", "set_attrs",
]
