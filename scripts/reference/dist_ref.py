"""Starts the ranks of a torch.distributed reference benchmark (bench_allreduce.py,
bench_step.py --world N)."""
import os
import socket
import sys

import torch.distributed as dist

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


def finish(q=None):
    """Ends a rank: all ranks meet, leave the process group, and rank 0's result is flushed
    from the queue; then the process exits at once. Left to the interpreter's exit, gloo's
    transport threads were sometimes still joinable when libtorch's statics were destroyed,
    and a rank aborted ("terminate called without an active exception") after its work was
    done, on a loaded machine."""
    dist.barrier()
    dist.destroy_process_group()
    if q is not None:
        q.close()
        q.join_thread()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)
