"""Starts the ranks of a torch.distributed reference benchmark (bench_allreduce.py,
bench_step.py --world N)."""
import socket
import sys

import torch.multiprocessing as mp


def spawn(world, rank_main, a, timeout=3600):
    """Runs rank_main(rank, a, port, queue) in `world` spawned processes that meet on a free
    loopback port, and returns what rank 0 put in the queue; exits if a rank failed."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    ctx = mp.get_context("spawn")
    q = ctx.Queue()
    procs = [ctx.Process(target=rank_main, args=(r, a, port, q)) for r in range(world)]
    for p in procs:
        p.start()
    out = q.get(timeout=timeout)
    for p in procs:
        p.join()
    if any(p.exitcode != 0 for p in procs):
        sys.exit("a rank failed")
    return out
