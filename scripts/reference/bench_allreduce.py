#!/usr/bin/env python3
"""The all-reduce of gdrf-bench allreduce in torch.distributed (Gloo over loopback): the
same tensors (--shapes, JSON), bucketed the same way (consecutive tensors flattened into
buckets of at most --bucket-kib KiB; a larger tensor alone), summed, divided by the world
size and copied back. One thread a rank; a barrier before each timed all-reduce. Prints
{"median_ms": [...]} (rank 0's medians, per bucket size) as JSON.
"""
import argparse
import json
import os
import statistics
import sys
import time

import torch
import torch.distributed as dist

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import dist_ref  # noqa: E402

def buckets(tensors, limit):
    out, start = [], 0
    while start < len(tensors):
        end, size = start + 1, tensors[start].numel() * 4
        while end < len(tensors) and size + tensors[end].numel() * 4 <= limit:
            size += tensors[end].numel() * 4
            end += 1
        out.append((start, end))
        start = end
    return out


def rank_main(rank, a, port, q):
    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=a.world)
    tensors = [torch.randn(s) for s in json.loads(a.shapes)]
    medians = []
    with torch.no_grad():
        for kib in [int(k) for k in a.bucket_kib.split(",")]:
            times = []
            for i in range(a.warmup + a.repeats):
                dist.barrier()
                t0 = time.perf_counter()
                for s, e in buckets(tensors, kib * 1024):
                    flat = torch.cat([t.reshape(-1) for t in tensors[s:e]])
                    dist.all_reduce(flat)
                    flat /= a.world
                    off = 0
                    for t in tensors[s:e]:
                        n = t.numel()
                        t.copy_(flat[off:off + n].view_as(t))
                        off += n
                if i >= a.warmup:
                    times.append((time.perf_counter() - t0) * 1e3)
            medians.append(statistics.median(times))
    if rank == 0:
        q.put(medians)
    dist_ref.finish(q)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--world", type=int, default=2)
    ap.add_argument("--shapes", required=True)
    ap.add_argument("--bucket-kib", required=True)
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--warmup", type=int, default=3)
    a = ap.parse_args()
    medians = dist_ref.spawn(a.world, rank_main, a, timeout=600)
    print(json.dumps({"median_ms": medians}))


if __name__ == "__main__":
    main()
