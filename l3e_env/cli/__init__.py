"""The `l3e` command line: parse, call the library, print."""
