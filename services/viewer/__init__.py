"""The live viewer (``psm view``): a Foxglove WebSocket server that forwards the cell's messages
unchanged, one channel per key, throttled per stream (docs/bus.md, *Live view*)."""
