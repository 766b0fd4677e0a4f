"""Re-chunking of the readers' blocks (io._common.validated_chunks): chunks of exactly chunk_size events in stream
order, and only the chunks that straddle two blocks are copies (a reader's blocks are large; copying each one whole
at every border would add a copy per event to reading, a real-time cost at VGA rates)."""
from __future__ import annotations

import numpy as np

from ti_cmax.events import Events
from ti_cmax.io._common import Block, validated_chunks


def test_chunks_are_exact_ordered_and_views_inside_a_block():
    sizes = [7, 25, 3, 40, 10, 1]
    t = np.arange(sum(sizes), dtype=float) * 1e-6
    blocks, start = [], 0
    for n in sizes:
        sl = slice(start, start + n)
        blocks.append(Block(Events(t[sl].copy(), np.full(n, 1, np.uint16), np.full(n, 2, np.uint16),
                                   np.ones(n, np.int8)), None, start))
        start += n
    chunks = list(validated_chunks(iter(blocks), "test", 4, 4, chunk_size=10))
    assert [len(c) for c in chunks] == [10] * 8 + [6]
    np.testing.assert_array_equal(np.concatenate([c.t for c in chunks]), t)
    # chunk 1 holds events 10..19, inside the second block (7..31): a view of it; chunk 0 straddles two blocks
    assert np.shares_memory(chunks[1].t, blocks[1].events.t)
    assert not np.shares_memory(chunks[0].t, blocks[0].events.t)
    assert np.shares_memory(chunks[4].t, blocks[3].events.t)  # events 40..49 of the block 35..74
