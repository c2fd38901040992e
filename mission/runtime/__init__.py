"""The mission runtime: the one mission loop and the two transports it drives (in process, or
every module its own process over Zenoh), the process set's supervisor, launcher, clock, inbox
and journal, and the mission manager's checkpoint."""
