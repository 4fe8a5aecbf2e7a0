"""Board detection and the coverage map: what each frame shows, and what the capture still lacks."""
