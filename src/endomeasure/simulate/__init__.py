"""The digital twin: a physically based renderer of prism-stereo endoscope images.

- :mod:`.preset` — presets (plain JSON files) and the ground-truth optics they define;
- :mod:`.truth_optics` — the simulator's own lens and biprism tracer (the truth);
- :mod:`.design` — a design space of probes: whole presets drawn from a seed;
- :mod:`.optics` — supersampled ray bundles through the truth optics, the apex image;
- :mod:`.targets` — chessboards and a textured metal surface with marks;
- :mod:`.scenes` — the image sets ``calib``, ``test``, ``scene`` (poses per seed);
- :mod:`.render` — shading, defocus, vignetting, apex band, sensor noise, 8 bits;
- :mod:`.truth` — the ground-truth JSON written next to every image.

``docs/simulator.md`` documents the model, the numbers of the default preset and the
accuracy of the rendered truth.
"""
