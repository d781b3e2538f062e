"""Releases: kept pairs as WebDataset shards, their changelog and datasheet (pure code).

``samples``: which pairs, what one sample holds, deterministic tar shards, packing and
content keys. ``datasheet``: the counts and the rejection breakdown of a release.
Orchestration is ``handedit.flows.release``; the layout is ``handedit.storage.releases``.
"""
