"""Service adapters of the PSM dataflow: each owns one process, its config and its Zenoh session."""
