"""Tools the tests share with `make bench`: the archive fuzzer and the fault-injection harness of the service."""
