"""The driver's scheduler: submit chunk nodes as their inputs complete, skip current ones.

The driver keeps the DAG itself rather than handing Prefect a static graph, because
only when a node's inputs are done does it know their digests, hence the node's
provenance key, hence whether the stored chunk is still current and can be skipped.
It is also the single writer of provenance: records arrive here and are written here.

A failed node (after its task's retries) does not stop anything: the driver writes its
frames' status with the failure's reason code and releases its dependents, which see a
non-OK upstream status and mark those frames ``UPSTREAM``.
"""

from __future__ import annotations

import queue
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Callable, Iterable

from handedit.flows.dag import Node, NodeId
from handedit.storage.provenance import is_current, provenance_key


@dataclass
class StageCounts:
    ran: int = 0
    skipped: int = 0
    failed: int = 0


@dataclass
class DagResult:
    records: dict[NodeId, dict]
    counts: dict[str, StageCounts] = field(default_factory=lambda: defaultdict(StageCounts))
    errors: list[str] = field(default_factory=list)


@dataclass
class Prepared:
    """A node ready to go: its key, the input fingerprints, its stage version and params."""

    node: Node
    key: str
    inputs: dict[str, str]
    version: int
    params: dict


def node_inputs(node: Node, records: dict[NodeId, dict]) -> dict[str, str]:
    inputs = dict(node.fixed_inputs)
    for dep in node.deps:
        outputs = records[(dep.unit, dep.chunk)].get("outputs", {})
        for name in dep.arrays:
            inputs[f"{dep.unit.path}#{dep.chunk}/{name}"] = outputs.get(name, "absent")
    return inputs


def run_dag(
    nodes: Iterable[Node],
    stage_params: Callable[[str], tuple[int, dict]],
    stored: Callable[[NodeId], dict | None],
    submit: Callable[[Prepared], object],
    complete: Callable[[Prepared, object], tuple[dict, bool]],
    prefail: Callable[[Prepared], dict | None],
    on_record: Callable[[Node, dict], None],
    progress: Callable[[], None] = lambda: None,
    on_idle: Callable[[float], None] = lambda idle_s: None,
    poll_s: float = 30.0,
) -> DagResult:
    """Run every node once its dependencies are done.

    ``submit`` starts a node and returns a handle with ``add_done_callback``;
    ``complete(prepared, handle)`` turns a finished handle into (record, failed);
    ``prefail`` may return a failure record without running (e.g. missing assets);
    ``on_record`` persists each new record (the driver's single write path);
    ``on_idle(seconds)`` is called every ``poll_s`` without a completion and may raise
    to abort (e.g. when the cluster has lost all its workers).
    """
    nodes = list(nodes)
    by_id = {n.id: n for n in nodes}
    waiting = {n.id: len({(d.unit, d.chunk) for d in n.deps}) for n in nodes}
    dependents: dict[NodeId, set[NodeId]] = defaultdict(set)
    for n in nodes:
        for d in n.deps:
            if (d.unit, d.chunk) not in by_id:
                raise ValueError(f"{n.unit.label}#{n.chunk} depends on {d.unit.label}#{d.chunk}, which is not planned")
            dependents[(d.unit, d.chunk)].add(n.id)
    result = DagResult(records={})
    done_q: queue.Queue = queue.Queue()
    in_flight = 0
    ready = [n.id for n in nodes if waiting[n.id] == 0]

    def finish(node_id: NodeId, record: dict) -> None:
        result.records[node_id] = record
        progress()
        for child in sorted(dependents[node_id]):
            waiting[child] -= 1
            if waiting[child] == 0:
                ready.append(child)

    while ready or in_flight:
        while ready:
            node = by_id[ready.pop()]
            version, params = stage_params(node.unit.stage)
            inputs = node_inputs(node, result.records)
            prep = Prepared(node, provenance_key(node.unit.stage, version, params, inputs), inputs, version, params)
            counts = result.counts[node.unit.stage]
            old = stored(node.id)
            if is_current(old, prep.key):
                counts.skipped += 1
                finish(node.id, old)
                continue
            failed = prefail(prep)
            if failed is not None:
                counts.failed += 1
                on_record(node, failed)
                finish(node.id, failed)
                continue
            handle = submit(prep)
            handle.add_done_callback(lambda _f, p=prep, h=handle: done_q.put((p, h)))
            in_flight += 1
        if in_flight:
            waited = 0.0
            while True:
                try:
                    prep, handle = done_q.get(timeout=poll_s)
                    break
                except queue.Empty:
                    waited += poll_s
                    on_idle(waited)
            in_flight -= 1
            record, failed = complete(prep, handle)
            counts = result.counts[prep.node.unit.stage]
            if failed:
                counts.failed += 1
                result.errors.append(f"{prep.node.unit.label}#{prep.node.chunk}: {record.get('error')}")
            else:
                counts.ran += 1
            on_record(prep.node, record)
            finish(prep.node.id, record)
    return result

