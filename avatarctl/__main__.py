from avatarctl.cli.app import main

main()
