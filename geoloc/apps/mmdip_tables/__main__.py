from geoloc.apps.mmdip_tables.command import main

main()
