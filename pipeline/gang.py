"""Native pieces of a gang launch (``Launcher.gang``): every CPU thread runs one long launch of the same
kernel, whose phases are separated by barriers and whose blocks are shared out as threads come free.

A phase hand-off through Python costs about 50 us (a sleeping core must be woken); these barriers
spin on one counter and cost about 0.1 us, and a thread that waits longer than a short spin yields
its core (``sched_yield``, whose address the launcher passes in), so a gang with more threads than
cores still makes progress. ``sync`` is zeroed before each launch: ``sync[0]`` counts arrivals at
barriers, ``sync[1 + phase]`` hands out the blocks of a phase. These are CPU-only (the compiler's
atomic builtins): compiled for CUDA, where a module's every function is built too, the barrier is
empty and ``next_block`` hands out nothing.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.func_native("""
#if !defined(__CUDA_ARCH__)
int* arrivals = sync.data;
const int target = threads * (phase + 1);
__atomic_add_fetch(arrivals, 1, __ATOMIC_ACQ_REL);
int spins = 0;
while (__atomic_load_n(arrivals, __ATOMIC_ACQUIRE) < target) {
    if (++spins < 4096) {
#if defined(__x86_64__) || defined(__i386__)
        __builtin_ia32_pause();
#endif
    } else {
        spins = 0;
        if (yield_address != 0) reinterpret_cast<wp::int32 (*)()>(yield_address)();
    }
}
#endif
""")
def barrier(sync: wp.array(dtype=int), phase: int, threads: int, yield_address: wp.uint64):
    """Wait until all ``threads`` have reached the barrier ending ``phase`` (phases numbered from 0,
    each thread passing every barrier in order); what they wrote before it is visible after it."""
    ...


@wp.func_native("""
#if !defined(__CUDA_ARCH__)
return __atomic_fetch_add(sync.data + 1 + phase, 1, __ATOMIC_RELAXED);
#else
return 2147483647;
#endif
""")
def next_block(sync: wp.array(dtype=int), phase: int) -> int:
    """The next unclaimed block of ``phase`` (0, 1, 2, ... across all threads); the caller stops once it
    is past the phase's block count."""
    ...
