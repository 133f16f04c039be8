"""What a person watches: TensorBoard events, a Weights & Biases run (optional) and console lines, written by
process 0 only.

    writer         the one interface (Writer, from summary_writer): each call to TensorBoard and, where the config
                   asks, to W&B, so both sinks get the same values at the same steps
    bucket_events  TensorBoard's event file in a bucket, as one object per flush (BucketEventFile)
    wandb_run      the W&B run: started or resumed, and never a step backwards (WandbRun, workdir/wandb.json)
    console        training's Monitor: its scalars and images, and its console line
    warn           how a sink's trouble is said: one warning line, and the run goes on

Training (Monitor), evaluation and the orbit call only the Writer. The package's door is Monitor, Writer and
summary_writer.
"""
from nerfpod.monitor.console import Monitor
from nerfpod.monitor.writer import Writer, summary_writer

__all__ = ["Monitor", "Writer", "summary_writer"]
