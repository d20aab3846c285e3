"""Physically based camera frames as the judge of the camera path (issue 28).

Frames rendered by Mitsuba 3 (a path tracer nobody on this project wrote) of the sample head
with textured skin, the kit's green balls (matte or glossy), OR lamps, drapes, gloved fingers,
steel and hair, through the calibrated lens, with exact truth from the scene geometry and a ray
cast per ball. Modules: :mod:`.spec` (what is in a scene, from a seed; the tuning / held-out
split), :mod:`.surfaces` (meshes, curves, textures), :mod:`.mitsuba_render` (the renderer; the
only module that needs Mitsuba, an optional extra), :mod:`.blender_render` (a second renderer,
Blender's Cycles, run in a Python of its own by :mod:`.blender_scene`, the only module importing
``bpy``), :mod:`.truth`, :mod:`.frameset` (sets on disk, camera conditions), :mod:`.build` (render
a set with either renderer, cache by scene hash, cut the committed crops).

Mitsuba is not a runtime dependency: the app never imports this package, the tests read the
committed renders, and the benchmark (``benchmarks/camera_pbr.py``) renders only what its cache
lacks.
"""
