"""How Taichi 1.7 runs parallel loops on a CPU, and the helper that works around it."""

from .runtime import ti

#: Taichi 1.7's smallest CPU task: a parallel loop gives each task at least this many iterations
#: (whatever ``block_dim`` says), so a loop over fewer items runs on one thread; and dispatching a
#: parallel loop to the thread pool costs ~50 us on a CPU even for one task, so such loops run
#: on the calling thread (``ti.loop_config(serialize=...)``) or are cut with :func:`chunk`.
CPU_TASK = 512


@ti.func
def chunk(it, n, chunks: ti.template()):
    """The items [begin, end) of iteration ``it`` of a parallel loop over n items: item ``it``
    itself, or with ``chunks`` > 0 (the CPU) the loop runs over chunks * CPU_TASK iterations and
    every CPU_TASK-th takes 1/chunks of the items (Taichi 1.7 gives each CPU task at least
    CPU_TASK iterations, so a loop over fewer items would run on one thread)."""
    begin = it
    end = it + 1
    if ti.static(chunks > 0):
        c = it // CPU_TASK
        begin = c * n // chunks
        end = ti.select(it % CPU_TASK == 0, (c + 1) * n // chunks, begin)
    return begin, end


def cpu_chunks(device) -> int:
    """How many pieces the hypothesis loop is cut into on taichi:cpu (four per CPU thread, so
    that a busy core does not hold up the others); 0 elsewhere (one GPU thread per lane group)."""
    if getattr(device, "arch", "") != "cpu":
        return 0
    return 4 * max(1, ti.lang.impl.current_cfg().cpu_max_num_threads)
