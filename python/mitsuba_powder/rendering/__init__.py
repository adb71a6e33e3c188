"""Rendering with Mitsuba: scene files that use the ``powder`` BSDF
(:mod:`~mitsuba_powder.rendering.render`, with the scene-description reading and editing in
:mod:`~mitsuba_powder.rendering.scene_description`), a virtual goniometer that measures the BRF
of a rendered patch (:mod:`~mitsuba_powder.rendering.gonio`, reports in
:mod:`~mitsuba_powder.rendering.gonio_report`), the white-furnace test
(:mod:`~mitsuba_powder.rendering.furnace`), and the comparison of a render with a photograph
(:mod:`~mitsuba_powder.rendering.photo`)."""
