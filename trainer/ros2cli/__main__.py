from trainer.ros2cli import main

main()
