"""Training campaigns: tool positions, the crash-safe snapshot store, the campaign loop.

- :mod:`.config` -- the campaign TOML (``[campaign]``, ``[pod]``, ``[anm]``, ``[cutting]`` ...).
- :mod:`.positions` -- tool positions on a surface group (pure numpy).
- :mod:`.store` -- the on-disk snapshot store (atomic, checksummed, rank-independent).
- :mod:`.run` -- the campaign loop: one full-order solve per position, resumable.
"""
