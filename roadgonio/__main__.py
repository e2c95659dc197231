import sys

from roadgonio.cli import main

sys.exit(main())
