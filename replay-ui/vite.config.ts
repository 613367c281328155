import { resolve } from "node:path";
import { fileURLToPath } from "node:url";
import vue from "@vitejs/plugin-vue";
import { defineConfig } from "vitest/config";

// The API serves dist/ at "/" and "/controller"; `npm run dev` proxies the API instead.
const api = process.env.MAPSERVICE_API ?? "http://127.0.0.1:8080";

const root = fileURLToPath(new URL(".", import.meta.url));

export default defineConfig({
  plugins: [vue()],
  base: "/",
  build: {
    outDir: "dist",
    rollupOptions: {
      input: {
        main: resolve(root, "index.html"),
        controller: resolve(root, "controller.html"),
      },
    },
  },
  server: {
    proxy: {
      "/api": { target: api, ws: true },
    },
  },
  test: {
    include: ["tests/**/*.test.ts"],
    environment: "node",
    // Generated-case tests take a second or two alone; on a loaded 2-core CI machine the
    // default 5 s turned a passing run into a timeout. Assertions decide, not the clock.
    testTimeout: 60_000,
  },
});
