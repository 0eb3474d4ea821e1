from dlocli.cli import main

main()
