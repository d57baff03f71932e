"""Memos for Taichi's compiler front end: the source it reads and the position text it builds.

Taichi 1.7's front end (Python AST → Taichi IR, run for every kernel instance in every process, with a
warm kernel cache too) formats a "File ..., line ..." message with the offending source line wrapped
by ``textwrap`` for every node it visits, to have it ready should that node fail to compile. The same
nodes are visited again and again (every unrolled ``ti.static`` iteration, every inlined ``ti.func``,
every instance of a kernel), and the text only depends on where the node is in its file, so
``memoize_source_positions`` caches it by that position: the front end gets the same strings, sooner
(docs/PERFORMANCE.md, "Cold start": about a quarter of a warm run's time to its first tracked frame).
It also reads a function's source lines from its file (``inspect.getsourcelines``, which tokenizes the
file's text) again for every instance; ``memoize_source_positions`` keeps them per function.
"""

from __future__ import annotations

_installed = False


def memoize_source_positions() -> bool:
    """Cache ``ASTTransformerContext.get_pos_info`` by node position; True when installed (once per process).
    Does nothing on a Taichi whose front end does not look the way this was written for."""
    global _installed
    if _installed:
        return True
    try:
        from taichi.lang.ast import ast_transformer_utils as utils
    except ImportError:
        return False
    context = getattr(utils, "ASTTransformerContext", None)
    original = getattr(context, "get_pos_info", None)
    if original is None:
        return False
    cache: dict = {}

    def get_pos_info(self, node):
        # Everything the original reads: the function's place in its file (its source is that file's),
        # and the node's kind and span (a For/While/If/FunctionDef span ends where its body starts).
        body = getattr(node, "body", None)
        key = (self.file, self.lineno_offset, self.indent, self.func.func.__name__, type(node), node.lineno,
               node.end_lineno, node.col_offset, node.end_col_offset, body[0].lineno if isinstance(body, list) and body else None)
        text = cache.get(key)
        if text is None:
            text = cache[key] = original(self, node)
        return text

    get_pos_info.__wrapped__ = original
    context.get_pos_info = get_pos_info
    _memoize_source_lines()
    _installed = True
    return True


def _memoize_source_lines() -> None:
    """Keep ``getsourcelines``'s answer per function (the function itself is the key, so a function that
    is gone cannot hand its source to a new one at the same address); the caller copies the list."""
    try:
        from taichi.lang import kernel_impl
    except ImportError:
        return
    original = getattr(kernel_impl, "getsourcelines", None)
    if original is None:
        return
    cache: dict = {}

    def getsourcelines(func):
        lines = cache.get(func)
        if lines is None:
            lines = cache[func] = original(func)
        return lines

    getsourcelines.__wrapped__ = original
    kernel_impl.getsourcelines = getsourcelines
