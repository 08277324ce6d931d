"""Field components: tri-plane encodings, rays and samples, volume rendering."""
