"""Natural scenes for SSR work (measured materials and lights, disjoint pools)."""
