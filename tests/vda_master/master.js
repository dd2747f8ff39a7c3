// An independent VDA 5050 2.0 master (coatyio vda-5050-lib MasterController, inbound and outbound topic
// validation on) for tests/test_vda5050_master.py: it connects to the test's broker, assigns orders to
// uagv/v2/palletpilot/<serial>, follows the AGV's state until the library reports each order processed, and
// prints one JSON summary line on stdout.
// Usage: node master.js PORT SERIAL ORDER_OR_SCENARIO_JSON_FILE TIMEOUT_S
// The file is one order, or a scenario {"steps": [...]} run step after step, each step
//   {"order": ORDER, "cancelAtNode": NODE_ID?, "restart": "here" | "last"?}
// - cancelAtNode: cancelOrder (an instant action) once the order's node NODE_ID is traversed;
// - restart: the order restarts where the truck stands after a cancel (VDA 5050 2.0 section 6.6.3.1): "here"
//   puts its first node (a temporary node) at the truck's position, "last" makes it the last node passed
//   with a deviation range (allowedDeviationXY) reaching the truck; its first node's nodePosition is given.
// The summary of a scenario has one entry per step under "steps".
"use strict";
const fs = require("fs");
const { MasterController, Topic } = require("vda-5050-lib");

const [port, serial, orderFile, timeoutS] = process.argv.slice(2);
const agvId = { manufacturer: "palletpilot", serialNumber: serial };
const order = JSON.parse(fs.readFileSync(orderFile, "utf8"));
const summary = {
  processed: false, error: null, byCancelation: null, actions: {}, loadsAfter: {}, errors: [],
  nodesTraversed: [], lastNodeId: null, states: 0,
};
let lastState = null;

const master = new MasterController(
  {
    interfaceName: "uagv",
    transport: { brokerUrl: `mqtt://127.0.0.1:${port}` },
    vdaVersion: "2.0.0",
    topicObjectValidation: { inbound: true, outbound: true },
  },
  { targetAgvs: agvId },
);

function finish(code) {
  if (lastState) {
    summary.lastNodeId = lastState.lastNodeId;
    summary.finalLoads = lastState.loads || [];
    summary.driving = lastState.driving;
  }
  process.stdout.write(JSON.stringify(summary) + "\n");
  master.stop().finally(() => process.exit(code));
}

setTimeout(() => { summary.error = `timeout after ${timeoutS} s`; finish(1); }, Number(timeoutS) * 1000);

function follow(order, step) {
  // assign one order; resolves with its summary when the library reports it processed
  const out = { processed: false, error: null, byCancelation: null, actions: {}, nodesTraversed: [], lastNodeId: null };
  return new Promise((resolve) => {
    master.assignOrder(agvId, order, {
      onOrderProcessed(withError, byCancelation, active, context) {
        out.processed = !withError && !active;
        out.error = withError ? String(withError.message || withError) : null;
        out.byCancelation = byCancelation;
        lastState = context.state;
        out.lastNodeId = context.state.lastNodeId;
        resolve(out);
      },
      onNodeTraversed(node) {
        out.nodesTraversed.push(node.nodeId);
        if (step && step.cancelAtNode === node.nodeId) {
          master.initiateInstantActions(agvId, { instantActions: [
            { actionId: `cancel-${order.orderId}`, actionType: "cancelOrder", blockingType: "HARD" },
          ] }, { onActionStateChanged() {}, onActionError(err) { summary.errors.push(`cancel: ${err.message || err}`); } });
        }
      },
      onActionStateChanged(actionState, withError, action, target, context) {
        const loads = (context.state.loads || []).map((l) => l.loadId || l.loadType || "");
        (out.actions[action.actionId] = out.actions[action.actionId] || []).push(actionState.actionStatus);
        if (actionState.actionStatus === "FINISHED") summary.loadsAfter[action.actionId] = loads;
        if (withError) summary.errors.push(`action ${action.actionId}: ${withError.message || withError}`);
      },
    }).catch((err) => { out.error = String(err && err.message ? err.message : err); resolve(out); });
  });
}

function restartFrom(order, how) {
  // the first node of an order after a cancel, from the last state (section 6.6.3.1)
  const first = order.nodes[0];
  const p = lastState.agvPosition;
  if (how === "here") {
    first.nodePosition = { x: p.x, y: p.y, mapId: p.mapId };
    order.edges[0].startNodeId = first.nodeId;
  } else {
    first.nodeId = lastState.lastNodeId;
    order.edges[0].startNodeId = first.nodeId;
    const d = Math.hypot(p.x - first.nodePosition.x, p.y - first.nodePosition.y);
    first.nodePosition.allowedDeviationXY = d + 0.3;
  }
}

const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

(async () => {
  await master.start();
  await master.subscribe(Topic.State, agvId, (state) => {
    summary.states += 1;
    lastState = state;
    for (const e of state.errors || []) summary.errors.push(`${e.errorType}: ${e.errorDescription || ""}`);
  });
  if (!order.steps) {
    const one = await follow(order, null);
    Object.assign(summary, one);
    finish(one.error ? 1 : 0);
    return;
  }
  summary.steps = [];
  for (const step of order.steps) {
    if (step.restart) {  // (the AGV answers a 2.0 master in 2.0 once it heard from it: a state came by now)
      while (lastState.driving) await sleep(100);
      restartFrom(step.order, step.restart);
    }
    const one = await follow(step.order, step);
    one.position = lastState.agvPosition;
    summary.steps.push(one);
    if (one.error) { finish(1); return; }
    if (step.cancelAtNode) { while (lastState.driving) await sleep(100); await sleep(500); }
  }
  summary.processed = summary.steps.every((s) => s.processed || s.byCancelation);
  finish(0);
})().catch((err) => { summary.error = String(err && err.stack ? err.stack : err); finish(1); });
