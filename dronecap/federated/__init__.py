"""dronecap.federated: FedAvg(M) across drones on Flower.

:mod:`~dronecap.federated.run` holds the settings and the Flower ClientApp/ServerApp;
:mod:`~dronecap.federated.engines` runs them (simulation or deployment);
:mod:`~dronecap.federated.fedavg` the strategy with exact
byte counting and the wire format; :mod:`~dronecap.federated.baselines` the single-drone and
centralized baselines; :mod:`~dronecap.federated.plot` the curves. Flower and torch are
imported inside the functions that need them.
"""
