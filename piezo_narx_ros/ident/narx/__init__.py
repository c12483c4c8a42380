"""The paper's NARX network: model, kernels, torch training, regressors, C emitter."""
