"""Photo → product mask: the classical chain (background model, edges, parts), its confidence, and
silhouette parts."""
