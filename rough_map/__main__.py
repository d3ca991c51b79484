from rough_map.cli.main import entry

entry()
