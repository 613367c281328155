// vda-5050-lib's own virtual vehicles and master controller, for mapservice's tests.
//
//   node fleet.cjs vehicle CONFIG.json   one AgvController + VirtualAgvAdapter; runs until
//                                        SIGTERM (a graceful stop) or SIGKILL (its connection
//                                        breaks: the broker publishes its last will)
//   node fleet.cjs master CONFIG.json    a MasterController that assigns each vehicle its
//                                        orders in turn, then exits
//
// Both print one JSON object per line on stdout ({"event": ...}) so the test can follow.
"use strict";

const fs = require("fs");
const { AgvController, MasterController, VirtualAgvAdapter } = require("vda-5050-lib");

function say(event) {
    process.stdout.write(JSON.stringify(event) + "\n");
}

function clientOptions(config) {
    return {
        interfaceName: config.interface,
        transport: { brokerUrl: config.broker, heartbeat: 5 },
        vdaVersion: config.vdaVersion || "2.0.0",
    };
}

async function vehicle(config) {
    const agvId = { manufacturer: config.manufacturer, serialNumber: config.serialNumber };
    const controller = new AgvController(agvId, clientOptions(config), {
        agvAdapterType: VirtualAgvAdapter,
        publishVisualizationInterval: config.visualizationMs,
    }, {
        initialPosition: { ...config.initialPosition, lastNodeId: "start" },
        initialBatteryCharge: config.batteryCharge,
        vehicleSpeed: config.speed,
        timeLapse: config.timeLapse,
    });
    await controller.start();
    say({ event: "started", agv: agvId });
    process.on("SIGTERM", async () => {
        await controller.stop();  // publishes OFFLINE on its connection topic
        say({ event: "stopped", agv: agvId });
        process.exit(0);
    });
}

async function master(config) {
    const controller = new MasterController(clientOptions(config), {});
    await controller.start();
    say({ event: "started" });
    await Promise.all(config.plans.map(async plan => {
        for (const order of plan.orders) {
            const processed = new Promise(resolve => {
                controller.assignOrder(plan.agv, order, {
                    onOrderProcessed: (withError, byCancelation, active) => resolve({
                        withError: withError ? withError.errorType : null, byCancelation, active,
                    }),
                }).catch(error => resolve({ withError: String(error), byCancelation: false }));
            });
            const outcome = await processed;
            say({ event: "processed", agv: plan.agv, orderId: order.orderId, ...outcome });
        }
    }));
    await controller.stop();
    say({ event: "done" });
    process.exit(0);
}

const [mode, configFile] = process.argv.slice(2);
const config = JSON.parse(fs.readFileSync(configFile, "utf8"));
const run = { vehicle, master }[mode];
if (!run) {
    process.stderr.write("usage: node fleet.cjs vehicle|master CONFIG.json\n");
    process.exit(2);
}
run(config).catch(error => {
    process.stderr.write(`${mode} failed: ${error && error.stack || error}\n`);
    process.exit(1);
});
