"""Running it across machines: the warm worker and fork server, the SuperNode and SuperExec, the
SuperLink's commands, certificates, the loopback federation, the Simulation Engine's runs, the grid."""
