import "leaflet/dist/leaflet.css";
import "./style.css";
import { createApp } from "vue";
import Controller from "./Controller.vue";

createApp(Controller).mount("#app");
