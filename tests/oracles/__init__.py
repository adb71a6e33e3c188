"""Independent references of the tests, each written once from docs/model.md (NumPy float64,
miepython, SciPy): they share no code with the product.

- :mod:`oracles.model`: the powder BRDF (every lobe), the surface Fresnel factor and the
  goniometric direction convention.
- :mod:`oracles.grains`: the grains' optics: Mie efficiencies and albedos, effective-medium
  mixing, Hapke's equivalent slab, the extrapolation ratio tau_o (two quadratures) and an
  independent reader of the bundled optical constants.
- :mod:`oracles.fit`: a multi-start least-squares fit of the model at one wavelength, the
  reference the product's fitter is judged against.
"""
