// The microphone, in the page's 24 kHz AudioContext, posted to the page in 40 ms blocks (960 samples).
"use strict";

class MicBlocks extends AudioWorkletProcessor {
  constructor() { super(); this.block = new Float32Array(960); this.filled = 0; }

  process(inputs) {
    const channel = inputs[0] && inputs[0][0];
    if (channel) {
      for (let i = 0; i < channel.length; i++) {
        this.block[this.filled++] = channel[i];
        if (this.filled === this.block.length) { this.port.postMessage(this.block.slice()); this.filled = 0; }
      }
    }
    return true;
  }
}

registerProcessor("mic-blocks", MicBlocks);
