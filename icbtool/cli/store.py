"""``icbtool store stats|check|evict DIR``: inspect, verify and trim a CRT-buffer store."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from icbtool.cli._common import int_at_least


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("store", help="inspect, verify or trim a CRT-buffer store")
    ss = p.add_subparsers(dest="store_command", metavar="ACTION", required=True)

    s = ss.add_parser("stats", help="records, bytes, per scene/light setup, octree occupancy")
    s.add_argument("dir", help="store directory")
    s.add_argument("--json", action="store_true", help="print JSON instead of a table")
    s.set_defaults(func=_stats)

    c = ss.add_parser("check", help="verify every payload checksum (exit 1 on damage)")
    c.add_argument("dir", help="store directory")
    c.add_argument("--repair", action="store_true", help="delete orphan payload files")
    c.add_argument("--drop-damaged", action="store_true", help="delete the rows of damaged records")
    c.add_argument(
        "--rebuild",
        action="store_true",
        help="rebuild a damaged or missing index database from the payloads (the old database "
        "is kept aside, damaged payloads are moved to quarantine/; nothing is deleted)",
    )
    c.set_defaults(func=_check)

    e = ss.add_parser(
        "evict",
        help="evict damaged records, then records down to a capacity (--max-records, "
        "--max-bytes; without either only damaged records go)",
    )
    e.add_argument("dir", help="store directory")
    e.add_argument(
        "--max-records", type=int_at_least(0), default=None, help="keep at most this many records"
    )
    e.add_argument(
        "--max-bytes", type=int_at_least(0), default=None, help="keep at most this many bytes"
    )
    e.add_argument(
        "--policy", choices=("lru", "least_hit", "farthest"), default="lru", help="who goes first"
    )
    e.add_argument(
        "--focus",
        type=float,
        nargs=3,
        default=None,
        metavar=("X", "Y", "Z"),
        help="current position for --policy farthest",
    )
    e.set_defaults(func=_evict)


def _open(path: str, readonly: bool):
    from pathlib import Path

    from icbtool import store

    p = Path(path)
    if not (p / store.store.DB_NAME).exists() and not (p / store.store.PAYLOAD_DIR).is_dir():
        raise FileNotFoundError(f"no icbtool store at {path}")
    return store.open(path, store.StoreConfig(readonly=readonly, create=False))


def _stats(args: argparse.Namespace) -> int:
    with _open(args.dir, readonly=True) as st:
        s = st.stats()
    if args.json:
        print(json.dumps(s, indent=2))
        return 0
    print(f"store {s['path']} (format {s['format_version']})")
    print(
        f"  records: {s['records']}   bytes: {s['bytes']:,}   "
        f"per record: {s['bytes_per_record']:,.0f}"
    )
    for g in s["groups"]:
        o = g["octree"] or {}
        print(
            f"  scene {g['scene_name']!r} {g['scene_hash'][:12]} light {g['light_hash'][:12]}: "
            f"{g['records']} records, {g['bytes']:,} bytes, {g['hits']} hits; octree depth "
            f"{o.get('depth')}, leaf {o.get('leaf_size', 0):.4g}, {o.get('occupied_leaves')} "
            f"leaves, {o.get('mean_per_leaf', 0):.2f} (max {o.get('max_per_leaf')}) per leaf"
        )
    return 0


def _rebuild(args: argparse.Namespace) -> int:
    from icbtool import store

    r = store.rebuild(args.dir)
    if not r.rebuilt and not r.damaged:
        n = len(r.recovered)
        print(
            f"the index of {r.path} is healthy and complete: left alone ({n} record(s) recovered)"
        )
    elif not r.rebuilt:
        print(
            f"the index of {r.path} is healthy: kept, without the rows of its "
            f"{len(r.damaged)} damaged record(s) ({len(r.recovered)} record(s) recovered)"
        )
    else:
        print(f"rebuilt the index of {r.path}: {len(r.recovered)} record(s) recovered")
    if r.old_index:
        print(f"  old index database kept as {r.old_index}")
    print(f"  hit counts restored from the old index for {r.hits_restored} record(s)")
    for d in r.damaged:
        rid = "?" if d.record_id is None else d.record_id
        print(f"  DAMAGED record {rid}: {d.problem} ({d.path})")
    if r.quarantined:
        print(f"  {len(r.quarantined)} damaged payload(s) moved to {Path(r.quarantined[0]).parent}")
    if r.orphans:
        print(f"  {len(r.orphans)} orphan file(s) (not payloads) left in payloads/")
    for old, new in sorted(r.renumbered.items()):
        print(f"  record {old} renumbered {new} (id already taken)")
    print("OK" if r.ok else f"DAMAGE: {len(r.damaged)} payload(s) not recovered")
    return 0 if r.ok else 1


def _check(args: argparse.Namespace) -> int:
    if args.rebuild:
        if args.repair or args.drop_damaged:
            raise ValueError(
                "store check: --rebuild cannot be combined with --repair/--drop-damaged"
            )
        return _rebuild(args)
    write = args.repair or args.drop_damaged
    with _open(args.dir, readonly=not write) as st:
        r = st.check(repair=args.repair, drop_damaged=args.drop_damaged)
    print(f"checked {r.records_checked} records; database integrity: {r.db_integrity}")
    for d in r.damaged:
        print(f"  DAMAGED record {d.record_id}: {d.problem} ({d.path})")
    if r.orphans:
        verb = "removed" if args.repair else "found (run with --repair to remove)"
        print(f"  {len(r.orphans)} orphan payload file(s) {verb}")
    if r.dropped_records:
        print(f"  dropped records {r.dropped_records}")
    print("OK" if r.ok else f"DAMAGE: {len(r.damaged)} record(s)")
    return 0 if r.ok else 1


def _evict(args: argparse.Namespace) -> int:
    with _open(args.dir, readonly=False) as st:
        if args.focus is not None:
            st.set_focus(args.focus)
        before = (len(st), st.total_bytes)
        damaged = st.evict_damaged(deep=True)  # damaged records go first, whatever the capacity
        gone = []  # without a capacity only the damaged records go
        if args.max_records is not None or args.max_bytes is not None:
            gone = st.evict(args.max_records, args.max_bytes, args.policy)
        if damaged:
            print(f"evicted {len(damaged)} damaged record(s) first: {damaged}")
        print(
            f"evicted {len(damaged) + len(gone)} records: {before[0]} -> {len(st)} records, "
            f"{before[1]:,} -> {st.total_bytes:,} bytes"
        )
    return 0
