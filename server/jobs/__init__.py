"""The job system: the jobs table as a queue, the supervisor, a process per job, and the tasks."""
