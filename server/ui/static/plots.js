// Live plots of one session's telemetry: uPlot charts over a sliding window. uPlot is loaded
// as a classic script (window.uPlot).

const WINDOW_S = 10;
/** A time this far back means another clock (a restarted server), not a torn sample, s. */
const RESTART_S = 5;
const COLORS = {
  hand: "#f2f2f2", feed: "#4fa3ff", lateral: "#ffb347", normal: "#7bd66f",
  amplitude: "#e070e0", frequency: "#6fd6d6", tick: "#4fa3ff", p99: "#ff6f6f",
  residence: "#ffd84f",
};

const CHARTS = [
  {
    id: "force", title: "Force (N)",
    series: [
      { label: "|F| hand", stroke: COLORS.hand, width: 2, get: (s) => s.hand_force_magnitude_N },
      { label: "feed", stroke: COLORS.feed, get: (s) => (s.resistive_N ? s.resistive_N[0] : null) },
      { label: "lateral", stroke: COLORS.lateral, get: (s) => (s.resistive_N ? s.resistive_N[1] : null) },
      { label: "normal", stroke: COLORS.normal, get: (s) => (s.resistive_N ? s.resistive_N[2] : null) },
    ],
  },
  {
    id: "vibration", title: "Vibration",
    series: [
      { label: "amplitude N", stroke: COLORS.amplitude, scale: "N", get: (s) => s.vibration_amplitude_N },
      { label: "frequency Hz", stroke: COLORS.frequency, scale: "Hz", get: (s) => s.vibration_frequency_Hz },
    ],
    axes: [{ scale: "N", label: "N" }, { scale: "Hz", label: "Hz", side: 1 }],
  },
  {
    id: "timing", title: "Server time per packet (µs)",
    series: [
      { label: "tick", stroke: COLORS.tick, get: (s) => s.tick_us_last },
      { label: "tick p99", stroke: COLORS.p99, get: (s) => s.tick_us_p99 },
      { label: "residence", stroke: COLORS.residence, get: (s) => (s.packet ? s.residence_us : null) },
    ],
  },
];

function axisStyle(extra = {}) {
  return { stroke: "#aab", grid: { stroke: "#2a2f3a" }, ticks: { stroke: "#2a2f3a" }, ...extra };
}

export class LivePlots {
  /** @param {HTMLElement} container */
  constructor(container) {
    this.container = container;
    this.charts = [];
    this.samples = 0;
    this.t0 = null;
    for (const spec of CHARTS) {
      const box = document.createElement("div");
      box.className = "chart";
      box.dataset.chart = spec.id;
      container.appendChild(box);
      const scales = { x: { time: false } };
      const axes = [axisStyle({ label: "s" })];
      if (spec.axes) {
        for (const a of spec.axes) {
          scales[a.scale] = { auto: true };
          axes.push(axisStyle({ scale: a.scale, label: a.label, side: a.side ?? 3 }));
        }
      } else {
        axes.push(axisStyle());
      }
      const opts = {
        title: spec.title,
        width: 400, height: 170,
        scales,
        axes,
        legend: { live: false },
        cursor: { drag: { x: false, y: false } },
        series: [{ label: "t s" }, ...spec.series.map((s) => ({
          label: s.label, stroke: s.stroke, width: s.width ?? 1.5, scale: s.scale, spanGaps: false,
        }))],
      };
      const data = [[], ...spec.series.map(() => [])];
      const plot = new window.uPlot(opts, data, box);
      this.charts.push({ spec, plot, data, box });
    }
    this.resize();
    new ResizeObserver(() => this.resize()).observe(container);
  }

  resize() {
    const width = Math.max(240, this.container.clientWidth - 8);
    for (const c of this.charts) c.plot.setSize({ width, height: 170 });
  }

  /** Drops every point (another session, or the session's stream restarted). */
  clear() {
    this.t0 = null;
    for (const c of this.charts) {
      for (const column of c.data) column.length = 0;
      c.plot.setData(c.data);
    }
  }

  /** Adds one telemetry sample (GET …/telemetry's JSON). */
  push(sample) {
    // A sample before any packet has no receive time: nothing to place on the time axis.
    if (!(sample.t_recv_s > 0)) return;
    if (this.t0 === null) this.t0 = sample.t_recv_s;
    const t = sample.t_recv_s - this.t0;
    const [first] = this.charts;
    const last = first && first.data[0].length ? first.data[0][first.data[0].length - 1] : null;
    if (last !== null && t < last) {
      // Far back: the clock restarted (another server): start over. Just behind: a sample
      // read while the loop wrote it (the telemetry allows torn reads): skipped, not a
      // reason to drop the window.
      if (last - t < RESTART_S) return;
      this.clear();
      this.t0 = sample.t_recv_s;
      this.push(sample);
      return;
    }
    for (const c of this.charts) {
      const [xs] = c.data;
      xs.push(t);
      c.spec.series.forEach((s, i) => c.data[i + 1].push(s.get(sample)));
      let drop = 0;
      while (drop < xs.length && xs[drop] < t - WINDOW_S) drop += 1;
      if (drop) for (const column of c.data) column.splice(0, drop);
    }
    this.samples += 1;
  }

  /** Redraws (once per animation frame at most). */
  draw() {
    for (const c of this.charts) c.plot.setData(c.data);
  }
}
