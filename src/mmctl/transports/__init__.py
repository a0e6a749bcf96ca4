"""Hardware transports: one subpackage per device, one module per wire protocol."""
