# Installed as the data package sb3_cgac.hyperparams (see setup.cfg), so that the YAML files ship with the package.
