"""The Python face of the ``powder`` BSDF: its properties read from JSON files
(:mod:`~mitsuba_powder.plugin.params`), the grain optics of its C++ Mie and Fresnel code called
in double precision (:mod:`~mitsuba_powder.plugin.grains`), its BRF evaluated at measurement
geometries (:mod:`~mitsuba_powder.plugin.brf`), and the colour a powder takes from its grains
(:mod:`~mitsuba_powder.plugin.appearance`). Every value comes from the compiled plugin; nothing
here re-implements its model."""
