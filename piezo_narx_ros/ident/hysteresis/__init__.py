"""
The envelope family (hysteresis-operator NARX).

model, kernels, training, model_file, stepper and export; mimo* and chains* are its forms on
several axes.
"""
