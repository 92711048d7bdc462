"""Suite-wide settings."""

import os

# The tiling probes of mehs's networks are cached per user (mehs.ssr.probe_cache);
# tests measure afresh unless a test points MEHS_CACHE_DIR at its own folder.
os.environ["MEHS_CACHE_DIR"] = ""
