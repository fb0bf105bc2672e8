from surgtrack.cli import main

main()
