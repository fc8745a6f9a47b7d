"""Compile profile of one ``octomerge`` command: how many XLA programs it compiles, how long each
takes, which are compiled more than once, and how many come from the persistent cache.

Runs the command in this process with JAX's compile log (``jax_log_compiles``) and its monitoring
events; the cache is the command line's own (``OCTOMERGE_CACHE_DIR``; ``off`` for none).

    OCTOMERGE_CACHE_DIR=off .venv/bin/python benchmarks/profile_compiles.py \\
        merge a.bt b.bt out.bt --xyz 0.4 -0.2 0 --rpy 0 0 0.75 --force
    .venv/bin/python benchmarks/profile_compiles.py --top 10 demo --no-figures --out-dir /tmp/demo
"""

from __future__ import annotations

import collections
import logging
import re
import sys
import time


class _Log(logging.Handler):
    def __init__(self):
        super().__init__(logging.DEBUG)
        self.messages: list[str] = []

    def emit(self, record):
        self.messages.append(record.getMessage())


def main(argv: list[str]) -> int:
    top = 25
    if argv[:1] == ["--top"]:
        top, argv = int(argv[1]), argv[2:]
    t0 = time.perf_counter()
    from octomerge_jax.cli.cache import use_fast_compile

    use_fast_compile()  # the command's XLA flags, before JAX starts
    import jax

    from octomerge_jax.cli import main as octomerge

    jax.config.update("jax_log_compiles", True)
    log = _Log()
    for name in ("jax._src.dispatch", "jax._src.interpreters.pxla", "jax._src.compiler"):
        lg = logging.getLogger(name)
        lg.addHandler(log)
        lg.setLevel(logging.DEBUG)
        lg.propagate = False
    hits = collections.Counter()
    jax.monitoring.register_event_listener(lambda event, **kw: hits.update([event]))
    rc = octomerge(argv)
    wall = time.perf_counter() - t0
    compiled = collections.defaultdict(list)
    for m in log.messages:
        r = re.search(r"Finished XLA compilation of (.+?) in ([0-9.e+-]+) s", m)
        if r:
            compiled[r.group(1)].append(float(r.group(2)))
    n = sum(len(v) for v in compiled.values())
    total = sum(sum(v) for v in compiled.values())
    again = sum(len(v) > 1 for v in compiled.values())
    print(f"\n`octomerge {' '.join(argv)}`: exit {rc}, {wall:.1f} s wall; {n} XLA programs of "
          f"{len(compiled)} functions ({again} built more than once) in {total:.1f} s, "
          f"{hits['/jax/compilation_cache/cache_hits']} of them loaded from the persistent cache\n")
    print("| function | programs | s (compile or load) |")
    print("|---|---|---|")
    for name, secs in sorted(compiled.items(), key=lambda kv: -sum(kv[1]))[:top]:
        print(f"| `{name}` | {len(secs)} | {sum(secs):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
